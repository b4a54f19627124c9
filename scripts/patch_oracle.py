#!/usr/bin/env python3
"""Upper bounds for source-modulating relighting on a `pixl synth` set (BENCHMARKS.md, "Demo weights vs baselines").

For every test pair i -> i+1 of each scene, scores (per-channel least-squares scale correction, PSNR,
SSIM with an 11-tap Gaussian window, sigma 1.5, as `pixl eval`):
  identity  - the source itself;
  patch16   - per 16x16 patch and channel, the best affine map of the source onto the *target*
              (least squares on the target: an oracle no network can beat if its modulation is
              constant per patch);
  patch8    - the same with 8x8 patches.
Usage: python3 scripts/patch_oracle.py SYNTH_DIR      (needs numpy and pillow)
"""
import json, sys, numpy as np
from PIL import Image
root=sys.argv[1]
m=json.load(open(f'{root}/scenes.json'))
def L(p): return np.array(Image.open(f'{root}/{p}').convert('RGB')).astype(np.float64)/255
def gauss(img, s=1.5, r=5):
    x=np.arange(-r,r+1); k=np.exp(-x**2/(2*s*s)); k/=k.sum()
    out=np.apply_along_axis(lambda v: np.convolve(v,k,mode='valid'),0,img)
    return np.apply_along_axis(lambda v: np.convolve(v,k,mode='valid'),1,out)
def ssim(a,b):
    C1,C2=0.01**2,0.03**2; vals=[]
    for c in range(3):
        x,y=a[...,c],b[...,c]
        mx,my=gauss(x),gauss(y); sxx=gauss(x*x)-mx*mx; syy=gauss(y*y)-my*my; sxy=gauss(x*y)-mx*my
        vals.append((((2*mx*my+C1)*(2*sxy+C2))/((mx*mx+my*my+C1)*(sxx+syy+C2))).mean())
    return np.mean(vals)
def psnr(a,b): return -10*np.log10(((a-b)**2).mean())
def scale(pred, gt):
    out=pred.copy()
    for c in range(3):
        p=pred[...,c].ravel(); g=gt[...,c].ravel()
        s=(p*g).sum()/max((p*p).sum(),1e-12); out[...,c]=p.reshape(pred.shape[:2])*s
    return np.clip(out,0,1)
def patch_affine(src,tgt,P):
    H,W,_=src.shape; out=np.zeros_like(src)
    for y in range(0,H,P):
        for x in range(0,W,P):
            for c in range(3):
                s=src[y:y+P,x:x+P,c].ravel(); t=tgt[y:y+P,x:x+P,c].ravel()
                A=np.stack([s,np.ones_like(s)],1)
                coef,*_=np.linalg.lstsq(A,t,rcond=None)
                out[y:y+P,x:x+P,c]=(A@coef).reshape(min(P,H-y),min(P,W-x))
    return np.clip(out,0,1)
r={}
for sc in m['scenes']:
    if sc['split']!='test': continue
    ims=[L(i['image']) for i in sc['images']]
    n=len(ims)
    for i in range(n):
        s,t=ims[i],ims[(i+1)%n]
        for name,pred in [('identity',s),('patch16',patch_affine(s,t,16)),('patch8',patch_affine(s,t,8))]:
            p=scale(pred,t); r.setdefault(name,[]).append((psnr(p,t),ssim(p,t)))
for k,v in r.items(): v=np.array(v); print(k, 'PSNR %.2f SSIM %.3f'%(v[:,0].mean(), v[:,1].mean()), len(v))
