//! Unidirectional path tracing with next-event estimation and MIS, writing Cycles' passes.
//!
//! Layers (pbrt-style): [`render`] (pixels in parallel with rayon, at least a row per task) →
//! `render_pixel` (samples of one pixel) → `trace_packet` (up to [`PACKET`] camera paths of
//! that pixel in lockstep, one vertex at a time, so that their camera, shadow and continuation
//! rays share BVH traversals as packets). `trace_packet` is compiled for packets of [`PACKET`],
//! 4 and 1 lanes, and a pixel's samples take the narrowest that holds them: the per-lane arrays
//! and sample numbers of a low-spp render (the first frames of a progressive preview) cost the
//! lanes it uses rather than sixteen (−14 % render time at 1 spp, −4 % at 4; git history of BENCHMARKS.md).
//!
//! Random numbers ([`crate::trace::sampler`], chosen by [`Renderer::sampler`]): each `(pixel, sample)`
//! asks for its uniforms by *dimension*, fixed per decision and bounce — pixel position
//! (dimension 0), lens position with depth of field (`sampler::dim::LENS`), then per bounce `b`
//! a block of five: light pick (1-D), light position (2-D),
//! BSDF lobe (1-D), BSDF direction (2-D), Russian roulette (1-D) (`sampler::dim`). The default
//! [`Sampler::Sobol`] gives every dimension its own padded, Owen-scrambled 2-D Sobol sequence
//! seeded per `(seed, pixel, dimension)`, so at 2^k spp each pair of a pixel is a (0,k,2)-net
//! (low discrepancy: error falling faster than `spp^-0.5`); [`Sampler::Independent`] draws
//! from the stream `Rng::for_stream(seed, [pixel, sample])` in call order (the earlier images,
//! bit for bit). Either way a sample's numbers depend only on `(seed, pixel, sample, dimension)`
//! and each sample keeps its own order of operations, so the image is bit-identical for a given
//! seed and sampler whatever the thread count, the scheduling or how rays are grouped (tested:
//! lockstep = each sample traced alone).
//!
//! Per path vertex: one light is picked by its estimated contribution at the vertex
//! ([`crate::trace::light::LightPick`]) and sampled (NEE; MIS with the BSDF pdf for area, sphere,
//! world, wide-sun and emissive-triangle lights, none for delta lights), then the BSDF is
//! sampled and the emission the new ray finds (area lights on the way, the surface hit, or the
//! world) is MIS-weighted with the light pdf of the vertex it left, pick probability included. Russian roulette from the fourth vertex on (survival `min(max β, 0.95)`).
//!
//! Bounces follow Cycles' `max_bounces`: with `max_bounces = B`, light is gathered at up to
//! `B + 1` surface vertices (0 = direct lighting only).
//!
//! Pass bookkeeping (see [`crate::trace::film`]): light arriving at the first hit is split between the
//! diffuse / glossy / transmission passes in proportion to each lobe's share of the BSDF value
//! (per channel) — for light sampling the lobe evaluations, for the continuing path the lobe
//! weights of the first sampled direction — and goes to `*Dir` when it comes straight from a
//! light, to `*Ind` otherwise.
use crate::error::{RenderError, Result};
use crate::math::V3;
use crate::scene::Scene;
use crate::trace::bvh::{Isa, Ray, RayPack, PACKET};
use crate::trace::camera::CameraRays;
use crate::trace::film::{Film, PixelSum};
use crate::trace::geometry::{Geometry, SurfaceHit};
use crate::trace::light::{LightPick, Lights, ShadingPoint};
use crate::trace::material::{Bsdf, BsdfEval, BsdfSample};
use crate::trace::sampler::{PacketSampler, Sampler};
use crate::trace::sampling::power_heuristic;
use std::sync::atomic::{AtomicUsize, Ordering};

/// How to render.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOptions {
    /// Samples per pixel.
    pub spp: u32,
    /// Output width; default the camera's (height follows the aspect ratio when only one is set).
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub seed: u64,
    /// Cycles' `max_bounces` (0 = direct light only).
    pub max_bounces: u32,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            spp: 16,
            width: None,
            height: None,
            seed: 0,
            max_bounces: 8,
        }
    }
}

impl RenderOptions {
    /// The output size for `scene`'s camera.
    pub fn resolution(&self, scene: &Scene) -> (u32, u32) {
        let (cw, ch) = (scene.camera.width, scene.camera.height);
        match (self.width, self.height) {
            (Some(w), Some(h)) => (w, h),
            (Some(w), None) => (w, ((w as f64 * ch as f64 / cw as f64).round() as u32).max(1)),
            (None, Some(h)) => (((h as f64 * cw as f64 / ch as f64).round() as u32).max(1), h),
            (None, None) => (cw, ch),
        }
    }
}

/// Everything a path needs, built once per render.
pub struct Renderer {
    pub geom: Geometry,
    pub lights: Lights,
    pub camera: CameraRays,
    pub width: u32,
    pub height: u32,
    pub opts: RenderOptions,
    /// Where the paths' uniform numbers come from ([`Sampler::Sobol`] unless changed).
    pub sampler: Sampler,
}

impl Renderer {
    /// Loads meshes and textures, builds the BVH and the light list.
    pub fn new(scene: &Scene, opts: &RenderOptions) -> Result<Renderer> {
        scene.validate()?;
        let (width, height) = opts.resolution(scene);
        if width == 0 || height == 0 || (width as usize).saturating_mul(height as usize) > pixl_core::io::MAX_PIXELS {
            return Err(RenderError::Options(format!(
                "render size {width}x{height} is empty or too large"
            )));
        }
        if opts.spp == 0 {
            return Err(RenderError::Options("spp must be at least 1".into()));
        }
        let mut geom = Geometry::build(scene)?;
        let lights = Lights::build(scene, &mut geom)?;
        let camera = CameraRays::new(&scene.camera, width, height);
        Ok(Renderer {
            geom,
            lights,
            camera,
            width,
            height,
            opts: opts.clone(),
            sampler: Sampler::default(),
        })
    }

    /// Renders all pixels (rows in parallel, each turned into the film's passes as soon as it
    /// is done); `progress(rows_done, rows_total)` is called after each row (from worker threads).
    pub fn render(&self, progress: &(dyn Fn(usize, usize) + Sync)) -> Film {
        let (w, h) = (self.width as usize, self.height as usize);
        let done = AtomicUsize::new(0);
        Film::from_rows(w, h, self.opts.spp, &|y, sums| {
            for (x, s) in sums.iter_mut().enumerate() {
                *s = self.render_pixel(x, y);
            }
            progress(done.fetch_add(1, Ordering::Relaxed) + 1, h);
        })
    }

    /// The sums of all samples of pixel `(x, y)`. Up to [`PACKET`] samples advance together,
    /// one path vertex at a time ([`Renderer::trace_packet`]), so their camera, shadow and
    /// bounce rays can share BVH traversals; each sample still draws its own numbers in the
    /// same order, so the result equals tracing them one by one.
    pub fn render_pixel(&self, x: usize, y: usize) -> PixelSum {
        #[cfg(target_arch = "x86_64")]
        if Isa::detect() >= Isa::Avx2 {
            // SAFETY: `Isa::detect` returns `Avx2` or more only after confirming every
            // feature `render_pixel_avx2` is compiled for on this CPU.
            return unsafe { self.render_pixel_avx2(x, y) };
        }
        self.render_pixel_body(x, y)
    }

    /// [`Renderer::render_pixel_body`] compiled with AVX2 (and what it implies): the shading
    /// code inlined into it (BSDF, light sampling, pass bookkeeping) uses the VEX encodings
    /// and `roundss` & co. FMA is enabled but rustc never contracts `a * b + c` into it, so
    /// the result is bit-identical to the baseline build (tested).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    fn render_pixel_avx2(&self, x: usize, y: usize) -> PixelSum {
        self.render_pixel_body(x, y)
    }

    #[inline(always)]
    fn render_pixel_body(&self, x: usize, y: usize) -> PixelSum {
        let mut acc = PixelSum::default();
        let pixel = (y * self.width as usize + x) as u64;
        let spp = self.opts.spp as usize;
        for s0 in (0..spp).step_by(PACKET) {
            let n = PACKET.min(spp - s0);
            // Low-spp renders' packets: as few lanes as they need, without the bookkeeping
            // (and the sample numbers) of the others.
            match n {
                1 => self.trace_packet::<1>(x, y, pixel, s0, n, &mut acc),
                2..=4 => self.trace_packet::<4>(x, y, pixel, s0, n, &mut acc),
                _ => self.trace_packet::<PACKET>(x, y, pixel, s0, n, &mut acc),
            }
        }
        acc
    }

    /// A ray leaving the surface at `hit` along `wi`. As in Cycles (3.2+), it starts exactly at
    /// the hit point and skips the triangle it leaves instead of being pushed off the surface:
    /// an offset would cross a surface that touches this one (a glass resting on a table) and
    /// leak light through geometry thinner than the offset.
    fn spawn(hit: &SurfaceHit, wi: V3) -> Ray {
        Ray::leaving(hit.prim, hit.p, wi)
    }

    /// Samples `s0..s0 + n` (`n ≤ L`, the lanes it is compiled for) of pixel `(x, y)`: each
    /// one camera path, its contribution to every pass added to `acc` (in sample order).
    ///
    /// The paths run in lockstep, one vertex at a time: every live path picks its light, then
    /// the light samples of all of them are drawn at once ([`Lights::sample_lanes`], which
    /// vectorises the solid-angle samples of rectangles across the lanes), then all their
    /// shadow rays are traced (as one packet when there are enough of them), then every path
    /// samples its BSDF, then all continuation rays are traced. Per path, the random numbers,
    /// the estimator and the order of its float operations are those of a path traced alone.
    #[inline(always)]
    fn trace_packet<const L: usize>(&self, x: usize, y: usize, pixel: u64, s0: usize, n: usize, acc: &mut PixelSum) {
        // A batch's rays fill the first slots of one `RayPack`.
        const { assert!(L >= 1 && L <= PACKET) };
        debug_assert!(n >= 1 && n <= L);
        let geom = &self.geom;
        let lights = &self.lights;
        let mut sums = [PixelSum::default(); L];
        // The samples' uniform numbers, lane j = sample s0 + j (each decision draws from its own
        // dimension; the live paths are at the same vertex).
        let mut smp = PacketSampler::<L>::start(self.sampler, self.opts.seed, pixel, s0 as u32, n, self.opts.spp);
        // Camera rays (lane = slot), one packet whatever their number; only the `n` samples of
        // this packet are traced (a low-spp render would otherwise pay for all PACKET lanes).
        let mut camera = Batch::<L>::new();
        for j in 0..n {
            let [u, v] = smp.camera(j);
            let (px, py) = (x as f32 + u, y as f32 + v);
            let ray = if self.camera.has_lens() {
                let [l1, l2] = smp.lens(j);
                self.camera.ray_lens(px, py, l1, l2)
            } else {
                self.camera.ray(px, py)
            };
            camera.push(j, ray, f32::INFINITY);
        }
        let mut hits = [None; L];
        camera.intersect(geom, 1, &mut hits);
        let mut paths: [Option<Path>; L] = std::array::from_fn(|_| None);
        for j in 0..n {
            paths[j] = self.camera_vertex(&camera.pack.ray(j), hits[j], &mut sums[j]);
        }
        let max_b = self.opts.max_bounces;
        // Per lane: the light the pending shadow ray carries, if unoccluded.
        let mut pending: [Option<Nee>; L] = [None; L];
        // Per lane, the closest hit of its continuation ray (set for the lanes that trace one).
        let mut next = [None; L];
        // Per iteration: shadow rays, continuation rays and the BSDF sample of each lane that
        // continues (a lane alive after the BSDF step has always written its entries, so
        // nothing is cleared between iterations).
        let (mut shadow, mut bounce) = (Batch::<L>::new(), Batch::<L>::new());
        let mut samples: [Option<BsdfSample>; L] = [None; L];
        // Per lane, the uniforms of its light sample at this vertex (pick, position).
        let mut light_u = [[0f32; 3]; L];
        // Per lane, its light sample at this vertex.
        let mut light_samples = [None; L];
        // Every live path is at vertex `depth` (all start at the camera hit and advance one
        // vertex per iteration).
        let mut depth = 0;
        loop {
            smp.begin_vertex(depth);
            // Russian roulette, then next-event estimation: light samples and shadow rays.
            shadow.len = 0;
            for j in 0..n {
                let Some(path) = &mut paths[j] else { continue };
                debug_assert_eq!(path.depth, depth);
                if depth >= 3 {
                    let q = path.beta.max_comp().min(0.95);
                    if !(smp.roulette(j) < q) {
                        paths[j] = None;
                        continue;
                    }
                    path.beta = path.beta / q;
                }
                path.pick = None;
                if path.bsdf.has_smooth() && !lights.is_empty() {
                    let (up, [u1, u2]) = smp.light(j);
                    light_u[j] = [up, u1, u2];
                    path.pick = Some(lights.pick_at(ShadingPoint {
                        p: path.hit.p,
                        n: path.bsdf.normal(),
                        two_sided: path.bsdf.transmits(),
                        solid_angle: depth == 0,
                    }));
                }
            }
            // The light samples of all lanes at once (see `Lights::sample_lanes`).
            {
                let mut lanes: [Option<(&mut LightPick, [f32; 3])>; L] = std::array::from_fn(|_| None);
                for ((lane, path), u) in lanes.iter_mut().zip(&mut paths[..n]).zip(&light_u) {
                    if let Some(Path { pick: Some(pick), .. }) = path {
                        *lane = Some((pick, *u));
                    }
                }
                lights.sample_lanes(geom, lanes, &mut light_samples);
            }
            for j in 0..n {
                let (Some(path), Some(ls)) = (&paths[j], light_samples[j]) else {
                    continue;
                };
                let e: BsdfEval = path.bsdf.eval(ls.wi);
                if !e.total().is_zero() && ls.pdf > 0.0 {
                    let tmax = if ls.dist.is_finite() {
                        ls.dist * (1.0 - 1e-3)
                    } else {
                        f32::INFINITY
                    };
                    let w = if ls.delta { 1.0 } else { power_heuristic(ls.pdf, e.pdf) };
                    pending[j] = Some(Nee {
                        e,
                        scale: ls.li * (w / ls.pdf),
                    });
                    shadow.push(j, Self::spawn(&path.hit, ls.wi), tmax);
                }
            }
            let occluded = shadow.occluded(geom);
            // Light of unoccluded shadow rays, then the BSDF sample of each path.
            bounce.len = 0;
            for j in 0..n {
                let Some(path) = &mut paths[j] else { continue };
                if let Some(nee) = pending[j].take() {
                    if !occluded[j] {
                        let (e, scale) = (nee.e, nee.scale);
                        if path.depth == 0 {
                            let parts = [e.diffuse, e.glossy, e.transmission];
                            let s = &mut sums[j];
                            for k in 0..3 {
                                s.dir[k] += parts[k] * scale;
                            }
                            s.combined += e.total() * scale;
                        } else {
                            let l = path.beta * e.total() * scale;
                            add_path_light(&mut sums[j], &path.frac, l, path.depth);
                        }
                    }
                }
                let (ul, [u1, u2]) = smp.bsdf(j);
                let Some(bs) = path.bsdf.sample(ul, u1, u2) else {
                    paths[j] = None;
                    continue;
                };
                let wt = bs.weight.total();
                if path.depth == 0 {
                    path.frac = [
                        bs.weight.diffuse.safe_div(wt),
                        bs.weight.glossy.safe_div(wt),
                        bs.weight.transmission.safe_div(wt),
                    ];
                }
                path.beta *= wt;
                if !path.beta.is_finite() || path.beta.is_zero() {
                    paths[j] = None;
                    continue;
                }
                bounce.push(j, Self::spawn(&path.hit, bs.wi), f32::INFINITY);
                samples[j] = Some(bs);
            }
            if bounce.len == 0 {
                break;
            }
            bounce.intersect(geom, MIN_BOUNCE_PACKET, &mut next);
            // Emission found by the continuation rays, and the next vertex.
            for j in 0..n {
                let (Some(path), Some(bs)) = (&mut paths[j], samples[j]) else {
                    continue;
                };
                let ray = &bounce.ray_of(j);
                let s = &mut sums[j];
                let next = next[j];
                let t_next = next.map(|h| h.t).unwrap_or(f32::INFINITY);
                // The light choice of the vertex the ray left (none: no light sampling there,
                // so the BSDF sample takes all the weight).
                let pick = path.pick.as_ref().filter(|_| !bs.delta);
                let (beta, frac, depth) = (path.beta, path.frac, path.depth);
                lights.area_hits(ray, t_next, |l, i, pdf, _| {
                    let w = mis(bs.pdf, pick, |pick| {
                        lights.pick_pmf_at(pick, i) * lights.area_dir_pdf(pick, i, pdf)
                    });
                    add_path_light(s, &frac, beta * l * w, depth);
                });
                let Some(h2) = next else {
                    if let Some(le) = lights.env_hit(ray.d) {
                        let w = mis(bs.pdf, pick, |pick| lights.env_pdf(pick, ray.d));
                        add_path_light(s, &frac, beta * le * w, depth);
                    }
                    lights.sun_hits(ray.d, |l, i, pdf| {
                        let w = mis(bs.pdf, pick, |pick| lights.pick_pmf_at(pick, i) * pdf);
                        add_path_light(s, &frac, beta * l * w, depth);
                    });
                    paths[j] = None;
                    continue;
                };
                let m2 = &geom.materials[geom.attrs[h2.prim as usize].material as usize];
                if m2.emission.max_comp() > 0.0 {
                    let cos_l = ray.d.dot(h2.ng).abs();
                    let w = mis(bs.pdf, pick, |pick| lights.tri_pdf(geom, pick, h2.prim, h2.t, cos_l));
                    add_path_light(s, &frac, beta * m2.emission * w, depth);
                }
                if depth >= max_b {
                    paths[j] = None;
                    continue;
                }
                path.depth += 1;
                let h2 = geom.mapped_normal(m2, h2);
                path.hit = h2;
                path.bsdf = Bsdf::new(m2, &h2, -ray.d);
                if path.bsdf.is_black() {
                    paths[j] = None;
                }
            }
            depth += 1;
        }
        for s in &sums[..n] {
            acc.add(s);
        }
    }

    /// What the camera ray of one sample sees before any bounce — lights in view, the world,
    /// the first surface's emission, depth, normal and colour passes — written to `s`; the path
    /// state at the first hit, or `None` when nothing is hit or it cannot scatter.
    #[inline(always)]
    fn camera_vertex(&self, camera_ray: &Ray, first: Option<SurfaceHit>, s: &mut PixelSum) -> Option<Path> {
        let lights = &self.lights;
        let t_first = first.map(|h| h.t).unwrap_or(f32::INFINITY);
        lights.camera_area_hits(camera_ray, t_first, |l, _, _, _| {
            s.emit += l;
            s.combined += l;
        });
        let Some(hit) = first else {
            if let Some(le) = lights.env_hit(camera_ray.d) {
                s.env += le;
                s.combined += le;
            }
            return None;
        };
        s.depth = self.camera.z_depth(hit.p);
        let geom = &self.geom;
        let mat = &geom.materials[geom.attrs[hit.prim as usize].material as usize];
        // The Normal pass holds the shading normal, bent by a normal map (as Cycles').
        let hit = geom.mapped_normal(mat, hit);
        s.normal = hit.ns;
        s.normal_n = 1;
        if mat.emission.max_comp() > 0.0 {
            s.emit += mat.emission;
            s.combined += mat.emission;
        }
        let bsdf = Bsdf::new(mat, &hit, -camera_ray.d);
        s.col = bsdf.colors;
        Some(Path {
            hit,
            bsdf,
            pick: None,
            frac: [V3::ZERO; 3],
            beta: V3::ONE,
            depth: 0,
        })
    }
}

/// The state of one camera path at its current vertex.
struct Path {
    hit: SurfaceHit,
    bsdf: Bsdf,
    /// The light choice at this vertex (set when it samples a light).
    pick: Option<LightPick>,
    /// Per-channel share of each lobe in the path throughput after the first bounce.
    frac: [V3; 3],
    beta: V3,
    /// The vertex's bounce count (0 = the camera hit).
    depth: u32,
}

/// Light a shadow ray brings if unoccluded: the BSDF evaluation and `Li · w / pdf`.
#[derive(Clone, Copy)]
struct Nee {
    e: BsdfEval,
    scale: V3,
}

/// Fewest rays of a batch traced as one packet; smaller batches go one by one (a packet's
/// cost depends little on how many of its lanes are live). Measured on the bench scene
/// (git history of BENCHMARKS.md).
const MIN_SHADOW_PACKET: usize = 4;
const MIN_BOUNCE_PACKET: usize = 8;

/// The rays of some lanes of a packet of paths, compacted into the first slots of a
/// [`RayPack`], for one BVH query. Its queries (and the light hit tests after them) are
/// `#[inline(always)]` so that they are compiled into the AVX2 pixel loop rather than as
/// separate baseline functions (render instructions −1.5 %, git history of BENCHMARKS.md).
struct Batch<const L: usize> {
    pack: RayPack,
    /// Lane of each ray, and slot of each lane's ray.
    lane: [u8; L],
    slot: [u8; L],
    len: usize,
}

impl<const L: usize> Batch<L> {
    fn new() -> Self {
        Batch {
            pack: RayPack::empty(),
            lane: [0; L],
            slot: [0; L],
            len: 0,
        }
    }

    #[inline(always)]
    fn push(&mut self, lane: usize, ray: Ray, tmax: f32) {
        self.pack.set(self.len, &ray, tmax);
        self.lane[self.len] = lane as u8;
        self.slot[lane] = self.len as u8;
        self.len += 1;
    }

    /// The ray of lane `lane` (which must have pushed one).
    #[inline(always)]
    fn ray_of(&self, lane: usize) -> Ray {
        self.pack.ray(self.slot[lane] as usize)
    }

    /// Mask of the filled slots.
    fn slots(&self) -> u32 {
        (1u32 << self.len) - 1
    }

    /// Per lane, whether its ray is occluded (`false` for lanes without a ray).
    #[inline(always)]
    fn occluded(&mut self, geom: &Geometry) -> [bool; L] {
        let mut out = [false; L];
        let k = self.len;
        if k >= MIN_SHADOW_PACKET {
            let slots = self.slots();
            geom.bvh.occluded_pack(&mut self.pack, slots, 0.0);
            for i in 0..k {
                out[self.lane[i] as usize] = self.pack.found(i);
            }
        } else {
            for i in 0..k {
                out[self.lane[i] as usize] = geom.occluded(&self.pack.ray(i), 0.0, self.pack.tmax(i));
            }
        }
        out
    }

    /// The closest hit of each ray, written to `out` at its lane (lanes without a ray are
    /// left as they are); batches of fewer than `min_packet` rays are traced one by one.
    #[inline(always)]
    fn intersect(&mut self, geom: &Geometry, min_packet: usize, out: &mut [Option<SurfaceHit>; L]) {
        let k = self.len;
        if k >= min_packet {
            let (slots, lane) = (self.slots(), &self.lane);
            geom.intersect_pack(&mut self.pack, slots, 0.0, |i, h| out[lane[i] as usize] = h);
        } else {
            for i in 0..k {
                out[self.lane[i] as usize] = geom.intersect(&self.pack.ray(i), 0.0, self.pack.tmax(i));
            }
        }
    }
}

/// MIS weight (power heuristic) of a BSDF sample of pdf `bsdf_pdf` that found a light, against
/// light sampling with the light choice `pick` of the vertex it left (`light_pdf(pick)`); 1 with
/// no light sampling to weigh against (no choice there, or a delta BSDF sample).
#[inline(always)]
fn mis(bsdf_pdf: f32, pick: Option<&LightPick>, light_pdf: impl FnOnce(&LightPick) -> f32) -> f32 {
    match pick {
        Some(pick) => power_heuristic(bsdf_pdf, light_pdf(pick)),
        None => 1.0,
    }
}

/// Adds light `l` (already times throughput and MIS weight) gathered at path vertex `depth`.
fn add_path_light(s: &mut PixelSum, frac: &[V3; 3], l: V3, depth: u32) {
    let target = if depth == 0 { &mut s.dir } else { &mut s.ind };
    for k in 0..3 {
        target[k] += l * frac[k];
    }
    s.combined += l;
}

/// Renders `scene` into Cycles-equivalent passes. `progress(rows_done, rows_total)` is called
/// from worker threads as rows finish.
pub fn render(scene: &Scene, opts: &RenderOptions, progress: &(dyn Fn(usize, usize) + Sync)) -> Result<Film> {
    let r = Renderer::new(scene, opts)?;
    Ok(r.render(progress))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every lobe and light kind: diffuse floor, rough metal-and-coat sphere, smooth glass box,
    /// an emissive quad, an area light in view, a sphere point light, a sun with a cone, a world.
    const SCENE: &str = r#"
        [camera]
        width = 24
        height = 16
        fov_y_deg = 50.0
        position = [0.0, 1.0, 4.0]
        look_at = [0.0, 0.3, 0.0]

        [[objects]]
        name = "floor"
        shape = { type = "quad", size = [8.0, 8.0] }
        transform = { rotate_deg = [-90.0, 0.0, 0.0] }
        material = { base_color = [0.7, 0.6, 0.5], roughness = 0.8 }

        [[objects]]
        name = "ball"
        shape = { type = "sphere", radius = 0.5 }
        transform = { translate = [-0.7, 0.5, 0.0] }
        material = { base_color = [0.9, 0.6, 0.3], roughness = 0.3, metallic = 0.5 }

        [[objects]]
        name = "glass"
        shape = { type = "cuboid", size = [0.6, 0.8, 0.6] }
        transform = { translate = [0.7, 0.4, 0.2] }
        material = { base_color = [0.5, 0.8, 0.9], roughness = 0.0, transmission = 1.0 }

        [[objects]]
        name = "panel"
        shape = { type = "quad", size = [0.5, 0.5] }
        transform = { translate = [0.0, 1.2, -1.5] }
        material = { base_color = [0.1, 0.1, 0.1], emission_color = [1.0, 0.8, 0.6], emission_strength = 3.0 }

        [[lights]]
        type = "area"
        position = [1.0, 2.5, 1.0]
        look_at = [0.0, 0.0, 0.0]
        size = 1.0
        power = 150.0
        visible_to_camera = true

        [[lights]]
        type = "point"
        position = [-1.5, 1.5, 1.5]
        power = 80.0
        radius = 0.2

        [[lights]]
        type = "sun"
        direction = [0.3, -1.0, -0.4]
        strength = 2.0
        angle_deg = 5.0

        [world]
        color = [0.2, 0.25, 0.3]
    "#;

    fn same(a: &PixelSum, b: &PixelSum) -> bool {
        let bits = |v: &V3| [v.x.to_bits(), v.y.to_bits(), v.z.to_bits()];
        let all = |s: &PixelSum| {
            let mut v = Vec::new();
            for k in 0..3 {
                v.extend(bits(&s.col[k]));
                v.extend(bits(&s.dir[k]));
                v.extend(bits(&s.ind[k]));
            }
            for x in [&s.emit, &s.env, &s.combined, &s.normal] {
                v.extend(bits(x));
            }
            v.push(s.depth.to_bits());
            v.push(s.normal_n);
            v
        };
        all(a) == all(b)
    }

    /// The lockstep render of a pixel's samples (shadow and continuation rays traced as
    /// packets) gives bit for bit what tracing each sample alone gives (one lane per call,
    /// every ray traced by single-ray traversal), for full and partial packets. On AVX2 CPUs
    /// this also compares the two builds of the shading code: `render_pixel` runs the AVX2
    /// one, `trace_packet` called from here the baseline one.
    #[test]
    fn lockstep_packets_equal_paths_traced_one_by_one() {
        let scene = Scene::from_toml_str(SCENE).expect("scene");
        // Full packets, a partial one of 16 lanes (21 = 16 + 5), of 4 lanes (3; 20 = 16 + 4).
        for (spp, sampler) in [
            (16, Sampler::Sobol),
            (21, Sampler::Sobol),
            (3, Sampler::Sobol),
            (20, Sampler::Sobol),
            (16, Sampler::Independent),
            (21, Sampler::Independent),
            (3, Sampler::Independent),
        ] {
            let opts = RenderOptions {
                spp,
                seed: 3,
                ..Default::default()
            };
            let mut r = Renderer::new(&scene, &opts).expect("renderer");
            r.sampler = sampler;
            let (mut lit, mut packed) = (0, 0);
            for y in 0..r.height as usize {
                for x in 0..r.width as usize {
                    let together = r.render_pixel(x, y);
                    let pixel = (y * r.width as usize + x) as u64;
                    let mut alone = PixelSum::default();
                    for s in 0..spp as usize {
                        r.trace_packet::<1>(x, y, pixel, s, 1, &mut alone);
                    }
                    assert!(same(&together, &alone), "pixel ({x}, {y}), spp {spp}, {sampler:?}");
                    assert!(together.combined.is_finite());
                    lit += (together.combined.max_comp() > 0.0) as usize;
                    packed += (together.ind.iter().any(|v| v.max_comp() > 0.0)) as usize;
                }
            }
            // The scene exercises what it should: lit pixels and indirect light (in fewer
            // pixels with 3 samples).
            let n = (r.width * r.height) as usize;
            let want = if spp >= 16 { n / 4 } else { n / 16 };
            assert!(
                lit == n && packed > want,
                "lit {lit}, with indirect light {packed} of {n}"
            );
        }
    }
}
