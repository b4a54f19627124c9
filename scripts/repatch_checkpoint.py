#!/usr/bin/env python3
"""Re-targets a pixl checkpoint (f32 safetensors) to another patch size, as a fine-tuning start.

Usage: python3 scripts/repatch_checkpoint.py IN.safetensors OUT.safetensors --patch P   (numpy only)

The model config in the metadata gets `"patch": P` (4, 8, 16 or 32); every tensor keeps its name
and value except the ones whose shape depends on the patch size, which are resampled so that each
filter's response to a constant image is unchanged:
  - `src_encoder.patch_embed.proj.weight` (d, 3, p, p): shrinking by r = p_old / P sums r x r blocks
    of taps; growing spreads each tap over an r x r block divided by r^2;
  - `cond_encoder.stages.{s}.downsample.1.weight`: a stage that stops downsampling (2x2 stride 2 ->
    1x1) sums its 4 taps; one that starts (1x1 -> 2x2) spreads its tap divided by 4.
The result is not a trained model at the new patch size -- it only starts nearer one than a
random initialisation does (BENCHMARKS.md, demo weights). Then, e.g.:
  pixl train --config finetune.toml    # [model] preset = "<a config file with patch = P>",
                                       #         init_weights = "OUT.safetensors"
"""
import argparse, json, struct, sys
import numpy as np

SIZES = (4, 8, 16, 32)


def read(path):
    with open(path, 'rb') as f:
        n = struct.unpack('<Q', f.read(8))[0]
        header = json.loads(f.read(n))
        data = f.read()
    meta = header.pop('__metadata__', {})
    tensors = {}
    for name, info in header.items():
        if info['dtype'] != 'F32':
            sys.exit(f"{path}: {name} is {info['dtype']}; only f32 checkpoints are supported")
        a, b = info['data_offsets']
        tensors[name] = np.frombuffer(data[a:b], dtype='<f4').reshape(info['shape']).copy()
    return meta, tensors


def write(path, meta, tensors):
    header, blobs, off = {'__metadata__': meta}, [], 0
    for name in sorted(tensors):
        raw = np.ascontiguousarray(tensors[name], dtype='<f4').tobytes()
        header[name] = {'dtype': 'F32', 'shape': list(tensors[name].shape), 'data_offsets': [off, off + len(raw)]}
        blobs.append(raw)
        off += len(raw)
    h = json.dumps(header, separators=(',', ':')).encode()
    h += b' ' * (-len(h) % 8)
    with open(path, 'wb') as f:
        f.write(struct.pack('<Q', len(h)))
        f.write(h)
        for b in blobs:
            f.write(b)


def resample(w, k):
    """(O, I, k0, k0) -> (O, I, k, k), preserving each filter's sum over its taps."""
    k0 = w.shape[-1]
    if k == k0:
        return w
    if k < k0:
        r = k0 // k
        return w.reshape(w.shape[0], w.shape[1], k, r, k, r).sum(axis=(3, 5))
    r = k // k0
    return np.repeat(np.repeat(w, r, axis=2), r, axis=3) / (r * r)


def downsamples(patch, s):
    return (4 << s) <= patch


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('src')
    ap.add_argument('dst')
    ap.add_argument('--patch', type=int, required=True, choices=SIZES)
    a = ap.parse_args()
    meta, t = read(a.src)
    if 'config' not in meta:
        sys.exit(f'{a.src}: no model config in the metadata; not a pixl checkpoint')
    cfg = json.loads(meta['config'])
    old = cfg.get('patch', 16)
    name = 'src_encoder.patch_embed.proj.weight'
    t[name] = resample(t[name], a.patch)
    for s in (1, 2, 3):
        name = f'cond_encoder.stages.{s}.downsample.1.weight'
        t[name] = resample(t[name], 2 if downsamples(a.patch, s) else 1)
    if a.patch == 16:
        cfg.pop('patch', None)
    else:
        cfg['patch'] = a.patch
    meta = dict(meta, config=json.dumps(cfg, separators=(',', ':')))
    write(a.dst, meta, t)
    print(f'{a.src} (patch {old}) -> {a.dst} (patch {a.patch})')


if __name__ == '__main__':
    main()
