//! `pixl-nn`: the project's own small layer over candle, covering what candle lacks.
//!
//! candle's fast inference kernels (`candle_nn::ops::layer_norm`, `softmax_last_dim`, `sdpa`,
//! `upsample_bilinear2d`) have no backward pass: gradients silently stop at the first three,
//! and the last fails in `backward()`. Every op here
//! dispatches on [`needs_grad`]: when any input tracks gradients (a `Var` or derived from one) it
//! takes a differentiable path built from candle primitives; otherwise it takes the fast path.
//! So inference is fast and training is correct, with no mode flag to forget.
//!
//! - [`norm`] — layer norm (last dim) and channel-first layer norm for ConvNeXt.
//! - [`ops`] — softmax, bilinear resize, GELU.
//! - [`rope`] — 2D rotary position embedding.
//! - [`linear`] — a candle `Linear` with the fused f32 path and an optional 8-bit one.
//! - [`mlp`] — Linear–GELU–Linear.
//! - [`vit`] — the pre-norm ViT block (attention, MLP, optional LayerScale and RoPE) that the
//!   PIXLRelight encoder and trunk and the DA3 backbone share.
//! - [`dpt`] — the reassemble and fusion stages of a DPT head, generic over the convolution.
//! - [`conv3x3`] — 3×3 convolution as L2-sized im2col tiles, one GEMM each, for inference.
//! - [`winograd`] — stride-1 3×3 convolution by Winograd's F(4×4, 3×3), for inference.
//! - [`dwconv`] — depthwise k×k convolution with its own forward and backward kernels.
//! - [`attention`] — multi-head scaled-dot-product attention (a fused, blocked CPU kernel for
//!   inference).
//! - [`conv_grad`], [`attention_grad`], [`norm_grad`], [`linear_grad`] — the training kernels:
//!   convolutions (and the stride-k transposed one), multi-head attention on fused qkv with RoPE,
//!   layer norm, and linear + bias + activation, each one candle op with its own CPU backward
//!   (f32; other devices and dtypes take the composed path).
//! - [`fastmath`] — vectorisable `exp`, row softmax, `erf` and GELU for the CPU kernels.
//! - [`fused`] — parallel fused bias/activation/residual/norm passes, a fused `Linear` and 1×1
//!   convolution (GEMMs in place over bias-filled outputs), the qkv head split with RoPE, and
//!   channels-first/last copies, for inference only (the model layers call them when no
//!   gradient is needed).
//! - [`packed`] — f32 linear layers with weights packed once for an AVX-512 kernel whose
//!   epilogue applies the bias, GELU and a layer-scaled residual add (ViT inference).
//! - [`int8`] — 8-bit linear layers (weights per channel, activations per row, AVX-512 VNNI) for
//!   faster CPU inference where the CPU has them.
//! - [`profile`] — wall time by operation kind, off unless switched on.
//! - [`testing`] — seeded test tensors and an f64 finite-difference gradient check.
pub mod attention;
pub mod attention_grad;
pub mod backbones;
pub mod conv3x3;
pub mod conv_grad;
pub mod dpt;
pub mod dwconv;
pub mod fastmath;
pub mod fused;
pub mod int8;
pub mod linear;
pub mod linear_grad;
pub mod mlp;
pub mod norm;
pub mod norm_grad;
pub mod ops;
pub mod packed;
pub mod profile;
pub mod rope;
pub mod testing;
pub mod vit;
pub mod winograd;

pub use attention::attention;
pub use dwconv::{depthwise_conv2d, DepthwiseConv2d};
pub use linear::Linear;
pub use mlp::Mlp;
pub use norm::{LayerNorm, LayerNorm2d};
pub use rope::Rope2d;

use candle_core::Tensor;

/// Whether any of `xs` takes part in a gradient computation.
pub fn needs_grad(xs: &[&Tensor]) -> bool {
    xs.iter().any(|t| t.track_op())
}

/// Has candle run its own generic CPU ops on the calling thread, by setting
/// `CANDLE_NUM_THREADS=1` unless the environment already sets it. candle 0.11 starts a pool of
/// pinned, spinning worker threads for its elementwise ops beside rayon's, which the kernels
/// here use; on few cores the two pools contend (a training step of the `small` network 7 %
/// slower on 2 cores, inference unchanged). Call at the start of `main`, before any candle op
/// and while the process has one thread.
pub fn prefer_rayon_pool() {
    if std::env::var_os("CANDLE_NUM_THREADS").is_none() {
        std::env::set_var("CANDLE_NUM_THREADS", "1");
    }
}

/// Keeps freed blocks of up to 32 MiB in the allocator for reuse, rather than returning them to
/// the system at once. glibc hands blocks above a threshold (128 KiB at first, adapting upwards)
/// to `mmap`, so every activation or gradient of a training step arrives as fresh pages, and
/// touching a fresh page costs about 2 µs: a narrow convolution's backward pass spent 19 ms of
/// its 22 ms there. With the threshold at 32 MiB those buffers are recycled (the same as
/// `GLIBC_TUNABLES=glibc.malloc.mmap_threshold=33554432`); memory above 64 MiB at the top of
/// the heap is still trimmed. Does nothing outside glibc, and leaves a threshold the
/// environment sets. Call at the start of `main`, as [`prefer_rayon_pool`].
pub fn recycle_freed_buffers() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let tunables = std::env::var("GLIBC_TUNABLES").unwrap_or_default();
        if tunables.contains("mmap_threshold") || std::env::var_os("MALLOC_MMAP_THRESHOLD_").is_some() {
            return;
        }
        // SAFETY: mallopt only changes the allocator's parameters; glibc documents it as callable
        // at any time.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
            libc::mallopt(libc::M_TRIM_THRESHOLD, 64 << 20);
        }
    }
}
