//! A fixed-bucket histogram of durations, kept by the control loop for the
//! call time of each component and the loop's lateness, and exported as
//! Prometheus histograms (`metrics`). Recording is a few comparisons and one
//! add on data the control thread owns: no lock, no atomic, no allocation.

/// Upper bounds of the buckets, nanoseconds (1 µs to 1 s, about three per
/// decade); the last bucket (`+Inf`) takes the rest.
pub const BUCKET_BOUNDS_NS: [u64; 19] = [
    1_000,
    2_500,
    5_000,
    10_000,
    25_000,
    50_000,
    100_000,
    250_000,
    500_000,
    1_000_000,
    2_500_000,
    5_000_000,
    10_000_000,
    25_000_000,
    50_000_000,
    100_000_000,
    250_000_000,
    500_000_000,
    1_000_000_000,
];

/// Counts of durations per bucket (not cumulative), their sum and count.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Histogram {
    /// `counts[i]` for `BUCKET_BOUNDS_NS[i]`; the last one past every bound.
    counts: [u64; BUCKET_BOUNDS_NS.len() + 1],
    sum_ns: u64,
    count: u64,
}

impl Histogram {
    /// Adds one duration.
    #[inline]
    pub fn record(&mut self, ns: u64) {
        let bucket = BUCKET_BOUNDS_NS.partition_point(|&bound| bound < ns);
        self.counts[bucket] += 1;
        self.sum_ns = self.sum_ns.saturating_add(ns);
        self.count += 1;
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    pub fn sum_ns(&self) -> u64 {
        self.sum_ns
    }

    /// (upper bound in seconds, count in that bucket alone) for every
    /// bucket; the last bound is infinity, which `prometheus-client`
    /// writes as `+Inf` (it adds the counts up itself).
    pub fn buckets_seconds(&self) -> Vec<(f64, u64)> {
        self.counts
            .iter()
            .enumerate()
            .map(|(i, &count)| (BUCKET_BOUNDS_NS.get(i).map_or(f64::INFINITY, |&ns| ns as f64 / 1e9), count))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_land_in_the_first_bucket_that_holds_them() {
        let mut h = Histogram::default();
        for ns in [0, 1_000, 1_001, 2_500, 999_999_999, 1_000_000_000, 1_000_000_001, u64::MAX] {
            h.record(ns);
        }
        let buckets = h.buckets_seconds();
        assert_eq!(buckets.len(), 20);
        // <= 1 µs: 0 and 1000; <= 2.5 µs: 1001 and 2500.
        assert_eq!(buckets[0], (1e-6, 2));
        assert_eq!(buckets[1], (2.5e-6, 2));
        // (0.5 s, 1 s]: two; past 1 s: two.
        assert_eq!(buckets[18], (1.0, 2));
        assert_eq!(buckets[19], (f64::INFINITY, 2));
        assert_eq!(buckets.iter().map(|b| b.1).sum::<u64>(), 8);
        assert_eq!(h.count(), 8);
        assert_eq!(h.sum_ns(), u64::MAX);
    }
}
