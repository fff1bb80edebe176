//! Small shared utilities: a seeded deterministic random generator and timers.

use std::path::{Path, PathBuf};
use std::time::Instant;

/// SplitMix64: tiny, fast, deterministic pseudo-random numbers for test geometry and benchmarks.
#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator with the given seed.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform integer in `0..n` (n > 0).
    pub fn below(&mut self, n: usize) -> usize {
        ((self.next_u64() as u128 * n as u128) >> 64) as usize
    }

    /// Standard Gaussian (mean 0, variance 1) by Box–Muller from two uniforms; deterministic.
    pub fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.next_f64(); // in (0, 1]: the logarithm stays finite
        let u2 = self.next_f64();
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
}

/// Seconds since `start`.
pub fn secs(start: Instant) -> f64 {
    start.elapsed().as_secs_f64()
}

/// Writes `bytes` to `path` atomically: into a temporary file beside it, then renamed over it,
/// creating the parent directories. The temporary name is unique to this process and call, so
/// threads or processes writing the same file at once (two tests building the same cached
/// basis, say, or generation shards sharing a volume) each rename a complete file and none
/// loses its temporary to another. The process id alone is not unique across containers (each
/// has its own PID namespace, so every shard may be PID 1): the name carries a random token
/// drawn once per process from the operating system as well.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), FileError> {
    use std::sync::atomic::{AtomicU64, Ordering};
    static NEXT: AtomicU64 = AtomicU64::new(0);
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(FileError::at("creating directory", parent))?;
    }
    let name = path
        .file_name()
        .ok_or_else(|| {
            FileError::new(
                "writing",
                path,
                std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a file path"),
            )
        })?
        .to_string_lossy();
    let tmp = path.with_file_name(format!(
        ".{name}.tmp{}-{:016x}-{}",
        std::process::id(),
        process_token(),
        NEXT.fetch_add(1, Ordering::Relaxed)
    ));
    std::fs::write(&tmp, bytes).map_err(FileError::at("writing", &tmp))?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        FileError::new("renaming to", path, e)
    })
}

/// A random number fixed for the life of this process (from the standard library's OS-seeded
/// hash keys), telling its temporary files apart from those of processes in other PID
/// namespaces that share a directory. Never used for anything that must be reproducible.
fn process_token() -> u64 {
    use std::hash::{BuildHasher, Hasher};
    static TOKEN: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *TOKEN.get_or_init(|| {
        let mut h = std::collections::hash_map::RandomState::new().build_hasher();
        h.write_u64(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos() as u64),
        );
        h.finish()
    })
}

/// The operating system refused to read, write or create a file or directory: what was being
/// done, the path and the system's reason.
#[derive(Debug, thiserror::Error)]
#[error("{action} {}: {source}", path.display())]
pub struct FileError {
    /// What was being done ("reading", "writing", "creating directory", …).
    pub action: &'static str,
    /// The path.
    pub path: PathBuf,
    /// The system's error.
    #[source]
    pub source: std::io::Error,
}

impl FileError {
    /// A file error.
    pub fn new(action: &'static str, path: &Path, source: std::io::Error) -> Self {
        Self {
            action,
            path: path.to_path_buf(),
            source,
        }
    }

    /// For `map_err`: `std::fs::read(&p).map_err(FileError::at("reading", &p))`.
    pub fn at<'a>(
        action: &'static str,
        path: &'a Path,
    ) -> impl FnOnce(std::io::Error) -> Self + 'a {
        move |source| Self::new(action, path, source)
    }
}

/// numpy-style linear-interpolation quantile of `values` (q in [0, 1]).
pub fn quantile(values: &[f64], q: f64) -> f64 {
    let mut v: Vec<f64> = values.to_vec();
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        return f64::NAN;
    }
    let h = (v.len() - 1) as f64 * q.clamp(0.0, 1.0);
    let lo = h.floor() as usize;
    let hi = (lo + 1).min(v.len() - 1);
    v[lo] + (h - lo as f64) * (v[hi] - v[lo])
}

/// The median of `values` ([`quantile`] at 0.5; NaN for none).
pub fn median(values: &[f64]) -> f64 {
    quantile(values, 0.5)
}

/// FNV-1a 64-bit hash of bytes (stable across platforms and runs).
pub fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}

/// [`fnv1a`] as 16 hex digits.
pub fn fnv1a_hex(bytes: &[u8]) -> String {
    format!("{:016x}", fnv1a(bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn concurrent_atomic_writes_of_one_file_all_land_whole() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub").join("same.bin");
        let contents: Vec<Vec<u8>> = (0..16u8).map(|i| vec![i; 100_000]).collect();
        std::thread::scope(|s| {
            for c in &contents {
                let path = &path;
                s.spawn(move || write_atomic(path, c).unwrap());
            }
        });
        let got = std::fs::read(&path).unwrap();
        assert!(contents.contains(&got), "the file is one whole write");
        let left: Vec<_> = std::fs::read_dir(path.parent().unwrap())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(
            left,
            vec![std::ffi::OsString::from("same.bin")],
            "no temporaries left"
        );
        let err = write_atomic(dir.path(), b"x").unwrap_err();
        assert!(err.to_string().contains("renaming to"), "{err}");
    }

    #[test]
    fn quantile_matches_numpy_linear() {
        // numpy.quantile([1, 2, 3, 4, 10], 0.8) == 5.2
        assert!((quantile(&[4.0, 1.0, 10.0, 3.0, 2.0], 0.8) - 5.2).abs() < 1e-12);
        assert_eq!(quantile(&[7.0], 0.3), 7.0);
    }
}
