//! A fixed-bucket histogram of durations, kept by the control loop for the
//! call time of each component and the loop's lateness, and exported as
//! Prometheus histograms (`metrics`). Recording is a few comparisons and one
//! add on data the control thread owns: no lock, no atomic, no allocation.

/// Bucket upper bounds are powers of two nanoseconds, from 2^10 ns
/// (1.024 µs) to 2^30 ns (1.07 s), one per doubling; a last bucket (`+Inf`)
/// takes the rest. Powers of two make finding the bucket one count of
/// leading zeros, with no branch on the hot path.
pub const FIRST_BOUND_LOG2: u32 = 10;
pub const LAST_BOUND_LOG2: u32 = 30;
/// Buckets, `+Inf` included.
pub const BUCKETS: usize = (LAST_BOUND_LOG2 - FIRST_BOUND_LOG2) as usize + 2;

/// The upper bound of bucket `i` in nanoseconds (`None` for `+Inf`).
pub fn bound_ns(i: usize) -> Option<u64> {
    (i < BUCKETS - 1).then(|| 1u64 << (FIRST_BOUND_LOG2 as usize + i))
}

/// Counts of durations per bucket (not cumulative), their sum and count.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Histogram {
    /// `counts[i]` for durations up to `bound_ns(i)`, above the bound
    /// before; the last one past every bound.
    counts: [u64; BUCKETS],
    sum_ns: u64,
    count: u64,
    max_ns: u64,
}

impl Histogram {
    /// Adds one duration.
    #[inline]
    pub fn record(&mut self, ns: u64) {
        // ceil(log2(ns)): durations in (2^(k-1), 2^k] land under 2^k.
        let log2 = u64::BITS - ns.saturating_sub(1).leading_zeros();
        let bucket = (log2.saturating_sub(FIRST_BOUND_LOG2) as usize).min(BUCKETS - 1);
        self.counts[bucket] += 1;
        self.sum_ns = self.sum_ns.saturating_add(ns);
        self.count += 1;
        self.max_ns = self.max_ns.max(ns);
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    pub fn sum_ns(&self) -> u64 {
        self.sum_ns
    }

    /// The longest duration recorded (0 when none was).
    pub fn max_ns(&self) -> u64 {
        self.max_ns
    }

    /// How many durations were surely longer than `ns`: the counts of the
    /// buckets that lie wholly above it (a bucket holding `ns` is not
    /// counted, so this is a lower bound, exact at a bucket's bound).
    pub fn count_above(&self, ns: u64) -> u64 {
        (1..BUCKETS).filter(|&i| bound_ns(i - 1).is_some_and(|lower| lower >= ns)).map(|i| self.counts[i]).sum()
    }

    /// (upper bound in seconds, count in that bucket alone) for every
    /// bucket; the last bound is infinity, which `prometheus-client`
    /// writes as `+Inf` (it adds the counts up itself).
    pub fn buckets_seconds(&self) -> Vec<(f64, u64)> {
        self.counts
            .iter()
            .enumerate()
            .map(|(i, &count)| (bound_ns(i).map_or(f64::INFINITY, |ns| ns as f64 / 1e9), count))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_land_in_the_first_bucket_that_holds_them() {
        let mut h = Histogram::default();
        for ns in [0, 1, 1_024, 1_025, 2_048, 2_049, (1 << 30) - 1, 1 << 30, (1 << 30) + 1, u64::MAX] {
            h.record(ns);
        }
        let buckets = h.buckets_seconds();
        assert_eq!(buckets.len(), 22);
        // Above 2^30 ns: (1 << 30) + 1 and u64::MAX; above 1024 ns: all but
        // 0, 1 and 1024.
        assert_eq!(h.count_above(1 << 30), 2);
        assert_eq!(h.count_above(1_024), 7);
        // <= 1.024 µs: 0, 1 and 1024; <= 2.048 µs: 1025 and 2048; then 2049.
        assert_eq!(buckets[0], (1.024e-6, 3));
        assert_eq!(buckets[1], (2.048e-6, 2));
        assert_eq!(buckets[2], (4.096e-6, 1));
        // <= 2^30 ns: two; past it: two.
        assert_eq!(buckets[20], ((1u64 << 30) as f64 / 1e9, 2));
        assert_eq!(buckets[21], (f64::INFINITY, 2));
        assert_eq!(buckets.iter().map(|b| b.1).sum::<u64>(), 10);
        assert_eq!(h.count(), 10);
        assert_eq!(h.sum_ns(), u64::MAX);
        assert_eq!(h.max_ns(), u64::MAX);
    }

    #[test]
    fn every_duration_is_at_most_its_bucket_bound_and_above_the_one_before() {
        for ns in (0..5000u64).chain((0..64).map(|k| 1u64 << k)).chain((1..64).map(|k| (1u64 << k) + 1)) {
            let mut h = Histogram::default();
            h.record(ns);
            let i = h.counts.iter().position(|&c| c == 1).unwrap_or(usize::MAX);
            assert!(bound_ns(i).is_none_or(|bound| ns <= bound), "{ns} in bucket {i}");
            assert!(i == 0 || bound_ns(i - 1).is_some_and(|below| ns > below), "{ns} in bucket {i}");
        }
    }
}
