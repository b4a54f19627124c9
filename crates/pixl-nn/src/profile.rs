//! Wall time by operation kind, for optimisation work: off by default, switched on by
//! [`enable`] (the `stage_times` example does it); when off, a [`span`] costs one relaxed
//! atomic load.
//!
//! Kinds are leaf operations as the CPU inference paths run them ("matmul", "attention",
//! "conv 3x3", "norm", …): spans must not nest, so each op records only its own time, and the
//! caller's total minus the sum of the kinds is whatever ran outside the instrumented ops
//! (candle's own elementwise ops, copies, reshapes). Times are the calling thread's wall time,
//! so an op's parallel work counts once.
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

static ENABLED: AtomicBool = AtomicBool::new(false);
static TOTALS: Mutex<BTreeMap<&'static str, (Duration, usize)>> = Mutex::new(BTreeMap::new());

/// Starts (or stops) recording spans.
pub fn enable(on: bool) {
    ENABLED.store(on, Ordering::Relaxed);
}

/// A running span: records its wall time under its kind when dropped.
pub struct Span {
    kind: &'static str,
    start: Option<Instant>,
}

impl Drop for Span {
    fn drop(&mut self) {
        if let Some(start) = self.start {
            let dt = start.elapsed();
            if let Ok(mut totals) = TOTALS.lock() {
                let e = totals.entry(self.kind).or_default();
                e.0 += dt;
                e.1 += 1;
            }
        }
    }
}

/// Times the current scope as `kind` (when recording is on).
pub fn span(kind: &'static str) -> Span {
    let start = ENABLED.load(Ordering::Relaxed).then(Instant::now);
    Span { kind, start }
}

/// The recorded totals `(kind, seconds, calls)`, and clears them.
pub fn take() -> Vec<(&'static str, f64, usize)> {
    let mut totals = match TOTALS.lock() {
        Ok(t) => t,
        Err(poisoned) => poisoned.into_inner(),
    };
    let out = totals.iter().map(|(k, (d, n))| (*k, d.as_secs_f64(), *n)).collect();
    totals.clear();
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spans_record_only_when_enabled() {
        take();
        {
            let _s = span("test kind");
        }
        assert!(take().is_empty());
        enable(true);
        {
            let _s = span("test kind");
            std::thread::sleep(Duration::from_millis(2));
        }
        enable(false);
        // Other tests of this crate may run kernels (and record their spans) meanwhile.
        let t: Vec<_> = take().into_iter().filter(|e| e.0 == "test kind").collect();
        assert_eq!(t.len(), 1);
        assert_eq!(t[0].2, 1);
        assert!(t[0].1 >= 0.002);
    }
}
