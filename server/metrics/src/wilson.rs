//! Ordinary success rates with 95 % Wilson score intervals: with three rollouts per task the normal
//! approximation is useless (0/3 would read as exactly 0 ± 0), Wilson stays inside [0, 1] and is honest at n = 3.
use serde::{Deserialize, Serialize};

/// z for a two-sided 95 % interval.
pub const Z_95: f64 = 1.959_963_984_540_054;

/// `successes / trials` with its 95 % Wilson interval (all `None` when there are no trials).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Proportion {
    pub successes: u64,
    pub trials: u64,
    pub rate: Option<f64>,
    pub wilson_low: Option<f64>,
    pub wilson_high: Option<f64>,
}

impl Proportion {
    pub fn new(successes: u64, trials: u64) -> Self {
        let (rate, low, high) = match wilson_interval(successes, trials, Z_95) {
            Some((lo, hi)) => (Some(successes as f64 / trials as f64), Some(lo), Some(hi)),
            None => (None, None, None),
        };
        Self { successes, trials, rate, wilson_low: low, wilson_high: high }
    }
}

/// Wilson score interval for `k` successes in `n` trials at normal quantile `z`.
pub fn wilson_interval(k: u64, n: u64, z: f64) -> Option<(f64, f64)> {
    if n == 0 || k > n {
        return None;
    }
    let n_f = n as f64;
    let p = k as f64 / n_f;
    let z2 = z * z;
    let denom = 1.0 + z2 / n_f;
    let centre = (p + z2 / (2.0 * n_f)) / denom;
    let half = z / denom * (p * (1.0 - p) / n_f + z2 / (4.0 * n_f * n_f)).sqrt();
    Some(((centre - half).max(0.0), (centre + half).min(1.0)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: (f64, f64), b: (f64, f64)) -> bool {
        (a.0 - b.0).abs() < 5e-5 && (a.1 - b.1).abs() < 5e-5
    }

    #[test]
    fn known_intervals() {
        // Reference values (e.g. R `binom::binom.wilson`, statsmodels `proportion_confint(method="wilson")`).
        assert!(close(wilson_interval(0, 3, Z_95).unwrap(), (0.0, 0.56151)));
        assert!(close(wilson_interval(3, 3, Z_95).unwrap(), (0.43849, 1.0)));
        assert!(close(wilson_interval(5, 10, Z_95).unwrap(), (0.23659, 0.76341)));
        assert!(close(wilson_interval(27, 90, Z_95).unwrap(), (0.21511, 0.40127)));
        assert_eq!(wilson_interval(0, 0, Z_95), None);
        let p = Proportion::new(1, 3);
        assert_eq!(p.rate, Some(1.0 / 3.0));
        assert!(p.wilson_low.unwrap() < 1.0 / 3.0 && p.wilson_high.unwrap() > 1.0 / 3.0);
    }
}
