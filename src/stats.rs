//! Small statistics shared by the evaluation and its tables: the Wilson
//! score interval of a success rate ([`wilson`]).

/// Wilson score interval of `k` successes in `n` trials at 95 %.
pub fn wilson(k: usize, n: usize) -> (f64, f64) {
    if n == 0 {
        return (f64::NAN, f64::NAN);
    }
    let z = 1.959_963_984_540_054_f64;
    let (n, p) = (n as f64, k as f64 / n as f64);
    let d = 1.0 + z * z / n;
    let c = (p + z * z / (2.0 * n)) / d;
    let h = z * ((p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt()) / d;
    // exact ends (rounding would leave p = 1 just outside its own interval)
    ((c - h).clamp(0.0, p), (c + h).clamp(p, 1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wilson_intervals_match_known_values() {
        let (lo, hi) = wilson(8, 10);
        assert!(
            (lo - 0.4902).abs() < 1e-3 && (hi - 0.9433).abs() < 1e-3,
            "{lo} {hi}"
        );
        let (lo, hi) = wilson(0, 8);
        assert!(lo == 0.0 && (hi - 0.3244).abs() < 1e-3);
        assert!(wilson(0, 0).0.is_nan());
    }
}
