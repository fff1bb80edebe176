//! The CRC-64 OpenIGTLink puts in every header: the ECMA-182 polynomial, most significant bit
//! first, initial value 0, no final XOR (what `igtl_util.c` computes), by a table built at compile
//! time. This module owns the polynomial, the table and the two functions over it.

/// The ECMA-182 generator polynomial (the `x^64` term implied).
pub const CRC64_POLY: u64 = 0x42F0_E1EB_A9EA_3693;

const CRC64_TABLE: [u64; 256] = crc64_table();

const fn crc64_table() -> [u64; 256] {
    let mut table = [0u64; 256];
    let mut byte = 0;
    while byte < 256 {
        let mut crc = (byte as u64) << 56;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & (1 << 63) != 0 {
                (crc << 1) ^ CRC64_POLY
            } else {
                crc << 1
            };
            bit += 1;
        }
        table[byte] = crc;
        byte += 1;
    }
    table
}

/// CRC-64 of `bytes` as OpenIGTLink computes it over a message body: ECMA-182 polynomial,
/// most significant bit first (not reflected), initial value 0, no final XOR
/// (the catalogue's CRC-64/ECMA-182; `crc64(b"123456789") == 0x6C40_DF5F_0B49_7347`).
pub fn crc64(bytes: &[u8]) -> u64 {
    crc64_update(0, bytes)
}

/// Continues a CRC-64 over more bytes: `crc64_update(crc64(a), b) == crc64(a ++ b)`.
pub fn crc64_update(crc: u64, bytes: &[u8]) -> u64 {
    bytes.iter().fold(crc, |crc, &byte| {
        let index = usize::from(((crc >> 56) as u8) ^ byte);
        CRC64_TABLE[index] ^ (crc << 8)
    })
}
