//! The paper's timing protocol (§4.1): a forward pass is run `warmups` times untimed (kernel
//! selection, allocator warm-up, lazy initialisation), then `runs` times timed; the figure reported
//! is the mean (the median is kept too, as it is robust to one preempted run).
//!
//! The closure is the unit of work. **The caller synchronises the device inside it** (e.g.
//! `device.synchronize()?` on CUDA/Metal, or reading back a scalar) so that asynchronous kernel
//! launches are counted; on the CPU candle is synchronous and nothing extra is needed. Intrinsic
//! estimation is not part of the timed work (paper: "intrinsic estimation excluded").
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Untimed warm-up runs of the paper's protocol.
pub const DEFAULT_WARMUPS: usize = 2;
/// Timed runs of the paper's protocol.
pub const DEFAULT_RUNS: usize = 5;

/// The result of [`time_runs`]: every timed run in milliseconds, and their mean and median.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Timing {
    /// Untimed runs that preceded the timed ones.
    pub warmups: usize,
    /// Wall-clock duration of each timed run, milliseconds, in run order.
    pub runs_ms: Vec<f64>,
    /// Arithmetic mean of `runs_ms` (NaN if there were no runs).
    pub mean_ms: f64,
    /// Median of `runs_ms`: the middle value, or the mean of the two middle values for an even
    /// count (NaN if there were no runs).
    pub median_ms: f64,
}

impl Timing {
    /// Statistics of already-measured durations (milliseconds). Factored out of [`time_runs`] so
    /// the statistics can be tested without a clock.
    pub fn from_runs(warmups: usize, runs_ms: Vec<f64>) -> Self {
        let n = runs_ms.len();
        let (mean_ms, median_ms) = if n == 0 {
            (f64::NAN, f64::NAN)
        } else {
            let mean = runs_ms.iter().sum::<f64>() / n as f64;
            let mut sorted = runs_ms.clone();
            sorted.sort_by(f64::total_cmp);
            let median = if n % 2 == 1 {
                sorted[n / 2]
            } else {
                0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
            };
            (mean, median)
        };
        Timing {
            warmups,
            runs_ms,
            mean_ms,
            median_ms,
        }
    }

    /// "123.4 ms (mean of 5 after 2 warm-ups; median 120.1 ms)".
    pub fn describe(&self) -> String {
        format!(
            "{:.1} ms (mean of {} after {} warm-ups; median {:.1} ms)",
            self.mean_ms,
            self.runs_ms.len(),
            self.warmups,
            self.median_ms
        )
    }
}

/// Runs `f` `warmups` times untimed, then `runs` times timed, and returns the timing. The first
/// error returned by `f` (warm-up or timed) stops the protocol and is returned as is.
pub fn time_runs<E>(warmups: usize, runs: usize, mut f: impl FnMut() -> Result<(), E>) -> Result<Timing, E> {
    for _ in 0..warmups {
        f()?;
    }
    let mut runs_ms = Vec::with_capacity(runs);
    for _ in 0..runs {
        let start = Instant::now();
        f()?;
        runs_ms.push(start.elapsed().as_secs_f64() * 1e3);
    }
    Ok(Timing::from_runs(warmups, runs_ms))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statistics_of_odd_count() {
        let t = Timing::from_runs(2, vec![5.0, 1.0, 3.0, 100.0, 2.0]);
        assert_eq!(t.mean_ms, (5.0 + 1.0 + 3.0 + 100.0 + 2.0) / 5.0);
        assert_eq!(t.median_ms, 3.0);
        assert_eq!(t.runs_ms, vec![5.0, 1.0, 3.0, 100.0, 2.0], "run order kept");
        assert_eq!(t.warmups, 2);
    }

    #[test]
    fn statistics_of_even_count() {
        let t = Timing::from_runs(0, vec![4.0, 1.0, 10.0, 2.0]);
        assert_eq!(t.mean_ms, 17.0 / 4.0);
        assert_eq!(t.median_ms, 3.0);
    }

    #[test]
    fn no_runs_is_nan_not_zero() {
        let t = Timing::from_runs(2, vec![]);
        assert!(t.mean_ms.is_nan() && t.median_ms.is_nan());
    }

    #[test]
    fn calls_warmups_plus_runs_times() {
        let mut calls = 0;
        let t = time_runs::<()>(2, 5, || {
            calls += 1;
            Ok(())
        })
        .unwrap();
        assert_eq!(calls, 7);
        assert_eq!(t.runs_ms.len(), 5);
        assert!(t.runs_ms.iter().all(|&ms| ms >= 0.0 && ms.is_finite()));
    }

    #[test]
    fn error_stops_the_protocol() {
        let mut calls = 0;
        let r = time_runs(DEFAULT_WARMUPS, DEFAULT_RUNS, || {
            calls += 1;
            if calls == 4 {
                Err("boom")
            } else {
                Ok(())
            }
        });
        assert_eq!(r, Err("boom"));
        assert_eq!(calls, 4);
    }
}
