//! NumPy `.npz` archives: a ZIP file (stored, no compression) of `.npy` arrays, format 1.0, little
//! endian, C order — what `numpy.load` reads with numpy alone.
//!
//! The writer is deterministic (fixed 1980-01-01 timestamps, arrays in the given order), so the same
//! arrays always give the same bytes. The reader accepts what the writer produces (stored entries,
//! `.npy` 1.0/2.0, the dtypes below) and reports anything else by name; it is for tests and for
//! tools that read datasets back.

use flate2::Crc;

/// Values of an array (the dtype).
#[derive(Debug, Clone, PartialEq)]
pub enum NpyData {
    /// `<f8`
    F64(Vec<f64>),
    /// `<f4`
    F32(Vec<f32>),
    /// `<i8`
    I64(Vec<i64>),
    /// `<i4`
    I32(Vec<i32>),
    /// `<u8` (unsigned 64-bit)
    U64(Vec<u64>),
    /// `|u1`
    U8(Vec<u8>),
}

impl NpyData {
    fn len(&self) -> usize {
        match self {
            NpyData::F64(v) => v.len(),
            NpyData::F32(v) => v.len(),
            NpyData::I64(v) => v.len(),
            NpyData::I32(v) => v.len(),
            NpyData::U64(v) => v.len(),
            NpyData::U8(v) => v.len(),
        }
    }

    fn descr(&self) -> &'static str {
        match self {
            NpyData::F64(_) => "<f8",
            NpyData::F32(_) => "<f4",
            NpyData::I64(_) => "<i8",
            NpyData::I32(_) => "<i4",
            NpyData::U64(_) => "<u8",
            NpyData::U8(_) => "|u1",
        }
    }

    fn bytes(&self) -> Vec<u8> {
        match self {
            NpyData::F64(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            NpyData::F32(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            NpyData::I64(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            NpyData::I32(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            NpyData::U64(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            NpyData::U8(v) => v.clone(),
        }
    }

    /// The values as f64 (for checks).
    pub fn to_f64(&self) -> Vec<f64> {
        match self {
            NpyData::F64(v) => v.clone(),
            NpyData::F32(v) => v.iter().map(|&x| x as f64).collect(),
            NpyData::I64(v) => v.iter().map(|&x| x as f64).collect(),
            NpyData::I32(v) => v.iter().map(|&x| x as f64).collect(),
            NpyData::U64(v) => v.iter().map(|&x| x as f64).collect(),
            NpyData::U8(v) => v.iter().map(|&x| x as f64).collect(),
        }
    }
}

/// A named n-dimensional array.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    /// Name in the archive (`numpy.load(f)[name]`), without `.npy`.
    pub name: String,
    /// Shape (C order); the product must equal the number of values.
    pub shape: Vec<usize>,
    /// Values.
    pub data: NpyData,
}

/// Why arrays could not be written to or read from `.npz` bytes.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NpzError {
    /// An array's shape does not hold its number of values.
    #[error("array {array}: shape {shape:?} holds {expected} values, got {got}")]
    ShapeMismatch {
        /// Array name.
        array: String,
        /// Its shape.
        shape: Vec<usize>,
        /// Values the shape holds ("overflow" when the product overflows).
        expected: String,
        /// Values given.
        got: usize,
    },
    /// Two arrays share a name.
    #[error("duplicate array name {0:?}: each array of an archive needs its own name")]
    DuplicateName(String),
    /// An array or the archive is over the 4 GiB ZIP limit (ZIP64 is not supported).
    #[error("{0} is over 4 GiB (ZIP64 not supported)")]
    TooLarge(String),
    /// One `.npy` entry is not readable (header, dtype, order or data).
    #[error("array {array}: {problem}")]
    Npy {
        /// Array name.
        array: String,
        /// What is wrong.
        problem: String,
    },
    /// The ZIP container is not readable (truncated, corrupt, compressed, CRC mismatch).
    #[error("not a readable .npz archive: {0}")]
    Archive(String),
}

impl NpyArray {
    /// An array; checks that the shape matches the number of values.
    pub fn new(name: impl Into<String>, shape: &[usize], data: NpyData) -> Result<Self, NpzError> {
        let name = name.into();
        let count = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
        if count != Some(data.len()) {
            return Err(NpzError::ShapeMismatch {
                array: name,
                shape: shape.to_vec(),
                expected: count.map_or_else(|| "overflow".into(), |c| c.to_string()),
                got: data.len(),
            });
        }
        Ok(Self {
            name,
            shape: shape.to_vec(),
            data,
        })
    }

    /// An (n, 3) f64 array from points.
    pub fn points(name: impl Into<String>, p: &[[f64; 3]]) -> Self {
        Self {
            name: name.into(),
            shape: vec![p.len(), 3],
            data: NpyData::F64(p.iter().flatten().copied().collect()),
        }
    }
}

/// Encodes one array as `.npy` (format 1.0, header padded to a multiple of 64 bytes).
pub fn encode_npy(a: &NpyArray) -> Vec<u8> {
    let shape = match a.shape.len() {
        1 => format!("({},)", a.shape[0]),
        _ => format!(
            "({})",
            a.shape
                .iter()
                .map(|s| s.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header = format!(
        "{{'descr': '{}', 'fortran_order': False, 'shape': {shape}, }}",
        a.data.descr()
    );
    // magic(6) + version(2) + length(2) + header + '\n' ≡ 0 (mod 64)
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(&a.data.bytes());
    out
}

/// Writes arrays into `.npz` bytes (ZIP, stored). Fails on duplicate names or entries over 4 GiB.
pub fn write_npz(arrays: &[NpyArray]) -> Result<Vec<u8>, NpzError> {
    let mut out = Vec::new();
    let mut central = Vec::new();
    let mut names = std::collections::HashSet::new();
    const DOS_TIME: u16 = 0;
    const DOS_DATE: u16 = (1 << 5) | 1; // 1980-01-01
    for a in arrays {
        if !names.insert(a.name.clone()) {
            return Err(NpzError::DuplicateName(a.name.clone()));
        }
        let name = format!("{}.npy", a.name);
        let data = encode_npy(a);
        let size = u32::try_from(data.len())
            .map_err(|_| NpzError::TooLarge(format!("array {}", a.name)))?;
        let offset =
            u32::try_from(out.len()).map_err(|_| NpzError::TooLarge("the archive".into()))?;
        let mut crc = Crc::new();
        crc.update(&data);
        let crc = crc.sum();
        let mut common = Vec::new();
        common.extend_from_slice(&20u16.to_le_bytes()); // version needed
        common.extend_from_slice(&0u16.to_le_bytes()); // flags
        common.extend_from_slice(&0u16.to_le_bytes()); // stored
        common.extend_from_slice(&DOS_TIME.to_le_bytes());
        common.extend_from_slice(&DOS_DATE.to_le_bytes());
        common.extend_from_slice(&crc.to_le_bytes());
        common.extend_from_slice(&size.to_le_bytes());
        common.extend_from_slice(&size.to_le_bytes());
        common.extend_from_slice(&(name.len() as u16).to_le_bytes());
        common.extend_from_slice(&0u16.to_le_bytes()); // extra length
        out.extend_from_slice(&0x0403_4b50u32.to_le_bytes());
        out.extend_from_slice(&common);
        out.extend_from_slice(name.as_bytes());
        out.extend_from_slice(&data);
        central.extend_from_slice(&0x0201_4b50u32.to_le_bytes());
        central.extend_from_slice(&20u16.to_le_bytes()); // version made by
        central.extend_from_slice(&common);
        central.extend_from_slice(&0u16.to_le_bytes()); // comment length
        central.extend_from_slice(&0u16.to_le_bytes()); // disk
        central.extend_from_slice(&0u16.to_le_bytes()); // internal attributes
        central.extend_from_slice(&0u32.to_le_bytes()); // external attributes
        central.extend_from_slice(&offset.to_le_bytes());
        central.extend_from_slice(name.as_bytes());
    }
    let cd_offset =
        u32::try_from(out.len()).map_err(|_| NpzError::TooLarge("the archive".into()))?;
    let entries = u16::try_from(arrays.len())
        .map_err(|_| NpzError::TooLarge(format!("{} arrays (limit 65535)", arrays.len())))?;
    out.extend_from_slice(&central);
    out.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    out.extend_from_slice(&entries.to_le_bytes());
    out.extend_from_slice(&entries.to_le_bytes());
    out.extend_from_slice(&(central.len() as u32).to_le_bytes());
    out.extend_from_slice(&cd_offset.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    Ok(out)
}

fn u16_at(b: &[u8], i: usize) -> Option<u16> {
    b.get(i..i + 2).map(|s| u16::from_le_bytes([s[0], s[1]]))
}

fn u32_at(b: &[u8], i: usize) -> Option<u32> {
    b.get(i..i + 4)
        .map(|s| u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
}

/// Decodes one `.npy` (format 1.0 or 2.0, C order, the dtypes of [`NpyData`]).
pub fn decode_npy(name: &str, b: &[u8]) -> Result<NpyArray, NpzError> {
    let bad = |m: String| NpzError::Npy {
        array: name.to_string(),
        problem: m,
    };
    if b.len() < 10 || &b[..6] != b"\x93NUMPY" {
        return Err(bad("not a .npy (magic \\x93NUMPY missing)".into()));
    }
    let (hlen, start) = match b[6] {
        1 => (
            u16_at(b, 8).ok_or_else(|| bad("header truncated".into()))? as usize,
            10,
        ),
        2 | 3 => (
            u32_at(b, 8).ok_or_else(|| bad("header truncated".into()))? as usize,
            12,
        ),
        v => return Err(bad(format!("unsupported .npy version {v}"))),
    };
    let header = b
        .get(start..start + hlen)
        .ok_or_else(|| bad("header truncated".into()))?;
    let header = std::str::from_utf8(header).map_err(|_| bad("header is not UTF-8".into()))?;
    let field = |key: &str| -> Result<&str, NpzError> {
        let i = header
            .find(&format!("'{key}':"))
            .ok_or_else(|| bad(format!("header has no '{key}'")))?;
        Ok(header[i + key.len() + 3..].trim_start())
    };
    let descr = field("descr")?;
    let descr = descr
        .strip_prefix('\'')
        .and_then(|d| d.split('\'').next())
        .ok_or_else(|| bad("descr is not a string".into()))?;
    if field("fortran_order")?.starts_with("True") {
        return Err(bad("Fortran order is not supported".into()));
    }
    let shape = field("shape")?;
    let shape = shape
        .strip_prefix('(')
        .and_then(|s| s.split(')').next())
        .ok_or_else(|| bad("shape is not a tuple".into()))?;
    let shape: Vec<usize> = shape
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse().map_err(|_| bad(format!("bad shape entry {s:?}"))))
        .collect::<Result<_, _>>()?;
    let count = shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| bad(format!("shape {shape:?} is too large")))?;
    let body = &b[start + hlen..];
    let need = |size: usize| -> Result<&[u8], NpzError> {
        let bytes = count
            .checked_mul(size)
            .ok_or_else(|| bad(format!("shape {shape:?} is too large")))?;
        body.get(..bytes).ok_or_else(|| {
            bad(format!(
                "data truncated: {count} values of {size} bytes need {}, got {}",
                count * size,
                body.len()
            ))
        })
    };
    let data = match descr {
        "<f8" => NpyData::F64(
            need(8)?
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
                .collect(),
        ),
        "<f4" => NpyData::F32(
            need(4)?
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
                .collect(),
        ),
        "<i8" => NpyData::I64(
            need(8)?
                .chunks_exact(8)
                .map(|c| i64::from_le_bytes(c.try_into().unwrap()))
                .collect(),
        ),
        "<i4" => NpyData::I32(
            need(4)?
                .chunks_exact(4)
                .map(|c| i32::from_le_bytes(c.try_into().unwrap()))
                .collect(),
        ),
        "<u8" => NpyData::U64(
            need(8)?
                .chunks_exact(8)
                .map(|c| u64::from_le_bytes(c.try_into().unwrap()))
                .collect(),
        ),
        "|u1" | "<u1" => NpyData::U8(need(1)?.to_vec()),
        d => return Err(bad(format!("unsupported dtype {d:?}"))),
    };
    NpyArray::new(name, &shape, data)
}

/// Reads every array of `.npz` bytes (stored entries only, as [`write_npz`] writes).
pub fn read_npz(bytes: &[u8]) -> Result<Vec<NpyArray>, NpzError> {
    let truncated = |i: usize| NpzError::Archive(format!("truncated at byte {i}"));
    let u16_ = |i: usize| u16_at(bytes, i).ok_or_else(|| truncated(i));
    let u32_ = |i: usize| u32_at(bytes, i).ok_or_else(|| truncated(i));
    // End of central directory: the last 22 bytes when there is no comment.
    let eocd = (0..bytes.len().saturating_sub(21))
        .rev()
        .find(|&i| u32_at(bytes, i) == Some(0x0605_4b50))
        .ok_or_else(|| {
            NpzError::Archive("not a ZIP archive (no end-of-central-directory record)".into())
        })?;
    let entries = u16_(eocd + 10)? as usize;
    let mut at = u32_(eocd + 16)? as usize;
    let mut out = Vec::with_capacity(entries);
    for k in 0..entries {
        if u32_(at)? != 0x0201_4b50 {
            return Err(NpzError::Archive(format!(
                "central directory entry {k} is corrupt (byte {at})"
            )));
        }
        let method = u16_(at + 10)?;
        let crc = u32_(at + 16)?;
        let size = u32_(at + 20)? as usize;
        let name_len = u16_(at + 28)? as usize;
        let extra = u16_(at + 30)? as usize;
        let comment = u16_(at + 32)? as usize;
        let local = u32_(at + 42)? as usize;
        let name = bytes
            .get(at + 46..at + 46 + name_len)
            .ok_or_else(|| NpzError::Archive("central directory truncated".into()))?;
        let name = String::from_utf8_lossy(name).to_string();
        if method != 0 {
            return Err(NpzError::Archive(format!(
                "entry {name} is compressed (method {method}); only stored entries are read"
            )));
        }
        let lname = u16_(local + 26)? as usize;
        let lextra = u16_(local + 28)? as usize;
        let start = local + 30 + lname + lextra;
        let data = bytes
            .get(start..start + size)
            .ok_or_else(|| NpzError::Archive(format!("entry {name} truncated")))?;
        let mut c = Crc::new();
        c.update(data);
        if c.sum() != crc {
            return Err(NpzError::Archive(format!("entry {name}: CRC mismatch")));
        }
        let array_name = name.strip_suffix(".npy").unwrap_or(&name);
        out.push(decode_npy(array_name, data)?);
        at += 46 + name_len + extra + comment;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npz_round_trips_and_is_deterministic() {
        let arrays = vec![
            NpyArray::points("p", &[[1.0, 2.0, 3.0], [4.0, 5.0, -6.5]]),
            NpyArray::new("k", &[3], NpyData::U8(vec![0, 1, 2])).unwrap(),
            NpyArray::new("i", &[2, 2], NpyData::I32(vec![-1, 2, 3, 4])).unwrap(),
            NpyArray::new("s", &[1], NpyData::U64(vec![u64::MAX])).unwrap(),
            NpyArray::new("e", &[0, 3], NpyData::F64(vec![])).unwrap(),
        ];
        let a = write_npz(&arrays).unwrap();
        assert_eq!(a, write_npz(&arrays).unwrap());
        assert_eq!(read_npz(&a).unwrap(), arrays);
        // Every .npy header is padded so the data starts 64-byte aligned within the entry.
        let npy = encode_npy(&arrays[0]);
        let hlen = u16::from_le_bytes([npy[8], npy[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0);
        assert!(NpyArray::new("x", &[2, 2], NpyData::U8(vec![1])).is_err());
        assert!(write_npz(&[arrays[0].clone(), arrays[0].clone()]).is_err());
        // A flipped byte in an entry's data fails its CRC; no flip or cut anywhere panics.
        let mut bad = a.clone();
        let first_data = 30 + "p.npy".len();
        bad[first_data + 64 + 3] ^= 0xff;
        assert!(read_npz(&bad).unwrap_err().to_string().contains("CRC"));
        for i in 0..a.len() {
            let mut b = a.clone();
            b[i] ^= 0x5a;
            let _ = read_npz(&b);
            let _ = read_npz(&a[..i]);
        }
    }
}
