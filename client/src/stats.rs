//! Figures the clients report: latency histograms and their percentiles, and gRPC status code
//! names.

use hdrhistogram::Histogram;

pub use librplus_proto::code_name;

/// A latency histogram in microseconds (1 µs to 1 h, three significant digits).
#[derive(Debug, Clone)]
pub struct Latencies(Histogram<u64>);

impl Default for Latencies {
    fn default() -> Self {
        Self::new()
    }
}

impl Latencies {
    /// An empty histogram.
    pub fn new() -> Self {
        Self(Histogram::new_with_bounds(1, 3_600_000_000, 3).expect("valid histogram bounds"))
    }

    /// Records one latency (clamped to the histogram's range).
    pub fn record(&mut self, d: std::time::Duration) {
        self.0
            .saturating_record(d.as_micros().clamp(1, u128::from(u64::MAX)) as u64);
    }

    /// Adds every value of another histogram.
    pub fn merge(&mut self, other: &Latencies) {
        self.0
            .add(&other.0)
            .expect("histograms with the same bounds merge");
    }

    /// Number of values recorded.
    pub fn count(&self) -> u64 {
        self.0.len()
    }

    /// Percentiles, mean and maximum in milliseconds (zeros when empty).
    pub fn summary(&self) -> LatencyMs {
        let h = &self.0;
        if h.is_empty() {
            return LatencyMs::default();
        }
        let ms = |us: u64| us as f64 / 1000.0;
        LatencyMs {
            p50: ms(h.value_at_quantile(0.50)),
            p95: ms(h.value_at_quantile(0.95)),
            p99: ms(h.value_at_quantile(0.99)),
            max: ms(h.max()),
            mean: h.mean() / 1000.0,
            count: h.len(),
        }
    }
}

/// Latency percentiles in milliseconds (as the JSON reports carry them).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct LatencyMs {
    /// Median.
    pub p50: f64,
    /// 95th percentile.
    pub p95: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Largest.
    pub max: f64,
    /// Mean.
    pub mean: f64,
    /// Number of values.
    pub count: u64,
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn percentiles_of_a_uniform_sample() {
        let mut l = Latencies::new();
        for ms in 1..=1000u64 {
            l.record(Duration::from_millis(ms));
        }
        let s = l.summary();
        assert_eq!(s.count, 1000);
        // Three significant digits: within 0.1 % of the exact order statistics.
        for (got, want) in [
            (s.p50, 500.0),
            (s.p95, 950.0),
            (s.p99, 990.0),
            (s.max, 1000.0),
        ] {
            assert!((got - want).abs() <= want * 1e-3, "{got} vs {want}");
        }
        assert!((s.mean - 500.5).abs() < 0.5, "{}", s.mean);
        let mut a = Latencies::new();
        a.record(Duration::from_millis(2000));
        a.merge(&l);
        assert_eq!(a.summary().count, 1001);
        assert!((a.summary().max - 2000.0).abs() <= 2.0);
        assert_eq!(Latencies::new().summary(), LatencyMs::default());
    }
}
