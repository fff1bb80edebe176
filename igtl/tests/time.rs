//! Header timestamps: 32.32 fixed point, saturation, and `SystemTime` conversion.

mod common;

use librplus_igtl::{timestamp_from_secs, timestamp_from_system_time, timestamp_to_secs};

#[test]
fn timestamps_are_32_32_fixed_point() {
    assert_eq!(timestamp_from_secs(1.5), 0x0000_0001_8000_0000);
    assert_eq!(timestamp_to_secs(0x0000_0001_8000_0000), 1.5);
    assert_eq!(
        timestamp_from_secs(1_700_000_000.25),
        (1_700_000_000u64 << 32) | 0x4000_0000
    );
    assert_eq!(timestamp_from_secs(-3.0), 0);
    assert_eq!(timestamp_from_secs(f64::NAN), 0);
    assert_eq!(timestamp_from_secs(1e30), u64::MAX);
    for secs in [0.0, 1e-9, 0.123_456_789, 1_234_567.891, 4_294_967_295.5] {
        let back = timestamp_to_secs(timestamp_from_secs(secs));
        assert!(
            (back - secs).abs() <= 2.4e-10 + secs * f64::EPSILON,
            "{secs} -> {back}"
        );
    }
    let t = std::time::UNIX_EPOCH + std::time::Duration::new(10, 500_000_000);
    assert_eq!(timestamp_from_system_time(t), (10u64 << 32) | 0x8000_0000);
    let before = std::time::UNIX_EPOCH - std::time::Duration::from_secs(1);
    assert_eq!(timestamp_from_system_time(before), 0);
}
