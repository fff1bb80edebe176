//! Header timestamps: 32.32 fixed-point seconds since the Unix epoch (integer part in the high 32
//! bits), converted to and from `f64` seconds and [`std::time::SystemTime`] by exact `2^32`
//! scaling.

const TWO_POW_32: f64 = 4_294_967_296.0;

/// Seconds since the Unix epoch to the header's 32.32 fixed-point timestamp, rounded to the
/// nearest `2^-32` s. Negative and NaN give 0 ("unused"); values past 2106 saturate.
pub fn timestamp_from_secs(secs: f64) -> u64 {
    // Float-to-integer `as` saturates and maps NaN to 0.
    (secs * TWO_POW_32).round() as u64
}

/// The header's 32.32 fixed-point timestamp to seconds since the Unix epoch.
pub fn timestamp_to_secs(timestamp: u64) -> f64 {
    (timestamp >> 32) as f64 + (timestamp & 0xFFFF_FFFF) as f64 / TWO_POW_32
}

/// A [`std::time::SystemTime`] as a header timestamp (0 before the epoch).
pub fn timestamp_from_system_time(time: std::time::SystemTime) -> u64 {
    match time.duration_since(std::time::UNIX_EPOCH) {
        Ok(since) => {
            let secs = since.as_secs().min(u64::from(u32::MAX));
            let frac = (u64::from(since.subsec_nanos()) << 32) / 1_000_000_000;
            (secs << 32) | frac
        }
        Err(_) => 0,
    }
}
