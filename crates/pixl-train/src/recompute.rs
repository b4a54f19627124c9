//! Loss and parameter gradients of one micro-batch, plain or with per-block gradient
//! checkpointing (recomputation). candle 0.11 has no autograd hooks, so checkpointing is done by
//! hand, segment by segment.
//!
//! The forward pass is cut into a chain of segments (pixl-model's segment API, see
//! `PixlRelight::prepare`):
//! `embed` (source patch + position embedding) → each `src_encoder` block → `fuse` (encoder
//! norm, the whole ConvNeXt intrinsics encoder, fusion MLP, registers) → each `trunk` block,
//! then the **tail** (readout norms, DPT head, modulation, loss) on the outputs of the four
//! readout blocks.
//!
//! [`checkpointed`]:
//! 1. runs every segment on the **detached** output of the previous one and keeps only that
//!    output (one `(B, tokens, d)` tensor per segment); each segment's graph is freed as soon as
//!    its output is detached;
//! 2. makes the four readout-block outputs fresh `Var` leaves, runs the tail with its graph and
//!    backpropagates the (divided) loss: gradients of the tail's parameters, and `∂L/∂out` at
//!    each readout;
//! 3. walks the segments in reverse: the segment's stored input becomes a fresh `Var`, the
//!    segment is recomputed with its graph, and `Σ out ⊙ G` is backpropagated, where `G` =
//!    `∂L/∂out` = the gradient the next segment passed back to its input (+ the readout gradient
//!    if the tail reads this output). Since `G` is a constant, this gives exactly the segment's
//!    share of `∂L/∂θ` and `∂L/∂input` (the chain rule); the input gradient becomes the previous
//!    segment's `G`.
//!
//! At most one segment's (or the tail's) graph is alive at a time, so the activation memory is
//! one block's plus the stored segment outputs plus the tail, instead of every block's. The cost
//! is a second forward of every segment. Every parameter belongs to exactly one segment, so its
//! gradient comes from one backward pass, summed over micro-batches in the same order as the
//! plain path. The recomputed forward is the same sequence of operations on the same values as
//! the plain `forward_unclipped` (CPU kernels are deterministic), so the loss is bitwise the
//! plain loss and the gradients differ only by the order of the floating-point sums where a
//! readout block output also feeds the next block.
use crate::error::{Result, TrainError};
use crate::loss::{loss, Objective};
use candle_core::{Tensor, Var};
use pixl_model::model::Prepared;
use pixl_model::PixlRelight;

/// What one micro-batch contributed.
#[derive(Clone, Debug, PartialEq)]
pub struct MicroReport {
    /// `total / divisor` (what was backpropagated).
    pub loss: f32,
    /// The L1 term (not divided).
    pub l1: f32,
    /// The perceptual term (not divided), when used.
    pub perceptual: Option<f32>,
}

/// One segment of the checkpointed chain.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Segment {
    Embed,
    SrcBlock(usize),
    Fuse,
    TrunkBlock(usize),
}

fn chain(model: &PixlRelight) -> Vec<Segment> {
    let mut segs = vec![Segment::Embed];
    segs.extend((0..model.src_encoder().depth()).map(Segment::SrcBlock));
    segs.push(Segment::Fuse);
    segs.extend((0..model.trunk().depth()).map(Segment::TrunkBlock));
    segs
}

fn run_segment(model: &PixlRelight, seg: Segment, input: Option<&Tensor>, p: &Prepared) -> Result<Tensor> {
    let input = || input.ok_or_else(|| TrainError::Other(format!("segment {seg:?} has no input")));
    Ok(match seg {
        Segment::Embed => model.src_encoder().embed(&p.src)?,
        Segment::SrcBlock(j) => model.src_encoder().block(j, input()?)?,
        Segment::Fuse => model.fuse_tokens(input()?, &model.cond_tokens(p)?)?,
        Segment::TrunkBlock(i) => model.trunk().block(i, input()?, &p.grid)?,
    })
}

/// Adds every gradient `store` holds for `vars[i]` to `grads[i]` (detached).
fn accumulate(store: &candle_core::backprop::GradStore, vars: &[Var], grads: &mut [Option<Tensor>]) -> Result<()> {
    for (acc, var) in grads.iter_mut().zip(vars) {
        if let Some(g) = store.get(var.as_tensor()) {
            let g = g.detach();
            *acc = Some(match acc.take() {
                None => g,
                Some(a) => (a + g)?.detach(),
            });
        }
    }
    Ok(())
}

fn add_opt(a: Option<Tensor>, b: Option<Tensor>) -> Result<Option<Tensor>> {
    Ok(match (a, b) {
        (Some(a), Some(b)) => Some((a + b)?.detach()),
        (a, b) => a.or(b),
    })
}

fn report(total: &Tensor, l1: f32, perceptual: Option<f32>) -> Result<MicroReport> {
    Ok(MicroReport {
        loss: total.to_scalar::<f32>()?,
        l1,
        perceptual,
    })
}

/// The plain path: `loss(model.forward_unclipped(src, ct), tgt, objective) / divisor`, one backward, the
/// gradients of `vars` added into `grads` (same length as `vars`).
#[allow(clippy::too_many_arguments)]
pub fn plain(
    model: &PixlRelight,
    src: &Tensor,
    ct: &Tensor,
    tgt: &Tensor,
    objective: &Objective,
    divisor: f64,
    vars: &[Var],
    grads: &mut [Option<Tensor>],
) -> Result<MicroReport> {
    let pred = model.forward_unclipped(src, ct)?;
    let terms = loss(&pred, tgt, objective)?;
    let total = (&terms.total / divisor)?;
    let store = total.backward()?;
    accumulate(&store, vars, grads)?;
    report(&total, terms.l1, terms.perceptual)
}

/// The same loss and (up to summation order) the same gradients as [`plain`], with per-block
/// recomputation (see the module docs).
#[allow(clippy::too_many_arguments)]
pub fn checkpointed(
    model: &PixlRelight,
    src: &Tensor,
    ct: &Tensor,
    tgt: &Tensor,
    objective: &Objective,
    divisor: f64,
    vars: &[Var],
    grads: &mut [Option<Tensor>],
) -> Result<MicroReport> {
    let p = model.prepare(src, ct)?;
    let segs = chain(model);
    let first_trunk = segs.len() - model.trunk().depth();
    let taps: Vec<usize> = model.trunk().readouts().iter().map(|&i| first_trunk + i).collect();

    // 1. Forward without keeping graphs: outputs[k] is segment k's output.
    let mut outputs: Vec<Option<Tensor>> = Vec::with_capacity(segs.len());
    let mut prev: Option<Tensor> = None;
    for &seg in &segs {
        let out = run_segment(model, seg, prev.as_ref(), &p)?.detach();
        outputs.push(Some(out.clone()));
        prev = Some(out);
    }
    drop(prev);

    // 2. The tail on leaves.
    let mut tap_grads: Vec<Option<Tensor>> = vec![None; segs.len()];
    let report = {
        let leaves = taps
            .iter()
            .map(|&k| match &outputs[k] {
                Some(t) => Ok(Var::from_tensor(t)?),
                None => Err(TrainError::Other(format!("readout segment {k} has no output"))),
            })
            .collect::<Result<Vec<Var>>>()?;
        let leaf_tensors: Vec<Tensor> = leaves.iter().map(|v| v.as_tensor().clone()).collect();
        let pred = model.tail_unclipped(&leaf_tensors, src, &p)?;
        let terms = loss(&pred, tgt, objective)?;
        let total = (&terms.total / divisor)?;
        let store = total.backward()?;
        accumulate(&store, vars, grads)?;
        for (&k, leaf) in taps.iter().zip(&leaves) {
            let g = store.get(leaf.as_tensor()).map(|g| g.detach());
            tap_grads[k] = add_opt(tap_grads[k].take(), g)?;
        }
        report(&total, terms.l1, terms.perceptual)?
    };

    // 3. Segments in reverse, each recomputed from its stored input.
    let mut g_next: Option<Tensor> = None;
    for k in (0..segs.len()).rev() {
        outputs[k] = None; // no longer needed: the recomputation below gives it again
        let Some(g_out) = add_opt(g_next.take(), tap_grads[k].take())? else {
            continue; // this segment's output does not reach the loss
        };
        let input = match k {
            0 => None,
            _ => match &outputs[k - 1] {
                Some(t) => Some(Var::from_tensor(t)?),
                None => return Err(TrainError::Other(format!("segment {k} lost its input"))),
            },
        };
        let out = run_segment(model, segs[k], input.as_ref().map(|v| v.as_tensor()), &p)?;
        let store = (out * g_out)?.sum_all()?.backward()?;
        accumulate(&store, vars, grads)?;
        g_next = match &input {
            Some(v) => store.get(v.as_tensor()).map(|g| g.detach()),
            None => None,
        };
    }
    Ok(report)
}
