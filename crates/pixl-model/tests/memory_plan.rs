//! `fullres::plan_memory` against a measured peak: a counting global allocator records the
//! largest number of heap bytes alive while `gain_bias_staged` runs (inputs included), for
//! `tiny` networks of patch 16 and 8 at several sizes and aspect ratios. The plan must not be
//! below the measurement (it is used to refuse requests that do not fit) and must stay close to
//! it (an honest figure, not a blanket overestimate).
use candle_core::{DType, Device, Tensor};
use pixl_model::fullres::{gain_bias_staged, plan_memory_threads, KERNEL_WORKSPACE_PER_THREAD};
use pixl_model::{build_inference, Config};
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = System.alloc(layout);
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::SeqCst) + layout.size();
            PEAK.fetch_max(now, Ordering::SeqCst);
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = System.alloc_zeroed(layout);
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::SeqCst) + layout.size();
            PEAK.fetch_max(now, Ordering::SeqCst);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout);
        LIVE.fetch_sub(layout.size(), Ordering::SeqCst);
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = System.realloc(ptr, layout, new_size);
        if !p.is_null() {
            if new_size >= layout.size() {
                let now = LIVE.fetch_add(new_size - layout.size(), Ordering::SeqCst) + new_size - layout.size();
                PEAK.fetch_max(now, Ordering::SeqCst);
            } else {
                LIVE.fetch_sub(layout.size() - new_size, Ordering::SeqCst);
            }
        }
        p
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Peak heap bytes above the level at the start, while building the inputs and running the
/// staged forward at `w × h`.
fn measured_peak(model: &pixl_model::PixlRelight, w: usize, h: usize) -> usize {
    let start = LIVE.load(Ordering::SeqCst);
    PEAK.store(start, Ordering::SeqCst);
    {
        let src = Tensor::from_vec(vec![0.5f32; 3 * w * h], (1, 3, h, w), &Device::Cpu).unwrap();
        let ct = Tensor::from_vec(vec![0.25f32; 9 * w * h], (1, 9, h, w), &Device::Cpu).unwrap();
        let (g, b) = gain_bias_staged(model, &src, &ct, &mut |_, _, _| {}).unwrap();
        // What relight_full keeps of them: the f32 vectors.
        let _v = (
            g.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            b.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        );
    }
    PEAK.load(Ordering::SeqCst) - start
}

#[test]
fn planned_bytes_bound_the_measured_peak_closely() {
    // Two worker threads, whatever the machine: each holds one convolution tile at a time, and
    // the plan is made for two. (Read when candle first uses the pool, below.)
    std::env::set_var("RAYON_NUM_THREADS", "2");
    let threads = 2;
    let workspace = (threads as u64 * KERNEL_WORKSPACE_PER_THREAD) as f64;
    let mut report = Vec::new();
    let mut cold = true;
    for patch in [16, 8] {
        let mut cfg = Config::tiny();
        cfg.patch = patch;
        let model = build_inference(&cfg, 0, DType::F32, &Device::Cpu).unwrap();
        for (w, h) in [(256, 192), (200, 136), (96, 320)] {
            let measured = measured_peak(&model, w, h) as f64;
            let plan = plan_memory_threads(&cfg, DType::F32, w, h, threads);
            // The weights were allocated before the measurement started. The kernels' workspace
            // is allocated by the first run in the process (as in `pixl relight`) and kept: the
            // later runs do not allocate it again.
            let mut planned = (plan.peak_bytes() - plan.weights) as f64;
            if !cold {
                planned -= workspace;
            }
            let ratio = planned / measured;
            report.push(format!(
                "patch {patch} {w}x{h}{}: planned {:.1} MB ({}), measured {:.1} MB, ratio {ratio:.2}",
                if cold { " (first run)" } else { "" },
                planned / 1e6,
                plan.peak().0,
                measured / 1e6
            ));
            // The first run also allocates the kernels' workspace, whose size follows the CPU's
            // caches (2.9 MB per thread on a Xeon with 2 MiB of L2 per core, less with smaller
            // caches); the plan allows the largest, so there the bound must hold and the rest of
            // the plan, without that allowance, must be as tight as in the later runs.
            assert!(ratio >= 1.0, "{}", report.join("\n"));
            let tight = if cold { (planned - workspace) / measured } else { ratio };
            assert!(tight < 1.25, "{}", report.join("\n"));
            cold = false;
        }
    }
    println!("{}", report.join("\n"));
}
