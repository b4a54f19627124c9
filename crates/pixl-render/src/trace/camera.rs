//! Camera rays (box pixel filter: uniform jitter inside the pixel). Pixel `(x, y)` has its
//! top-left corner at `(x, y)`; row 0 is the top of the image. The camera looks down −Z.
//!
//! A pinhole by default ([`CameraRays::ray`]). With depth of field ([`crate::scene::Dof`]) a
//! thin lens as in Cycles ([`CameraRays::ray_lens`]): the ray of image point `p` leaves a point
//! `L` of the aperture disk (radius `A`, in the camera's XY plane, uniform by the concentric map
//! of its own two uniforms) towards the point where the pinhole ray of `p` crosses the plane in
//! focus (camera depth `focus_distance`). So that plane is imaged sharply, and a point at depth
//! `z` is seen from pixel positions spread over a disk of radius `f·A·|1/focus − 1/z|` pixels.
use crate::math::V3;
use crate::scene::Camera;
use crate::trace::bvh::Ray;
use crate::trace::sampling::concentric_disk;

#[derive(Clone, Copy, Debug)]
pub struct CameraRays {
    pub origin: V3,
    right: V3,
    up: V3,
    /// Unit viewing direction (the camera's −Z).
    pub forward: V3,
    focal: f32,
    cx: f32,
    cy: f32,
    /// Aperture radius in metres (0: a pinhole) and the distance in focus.
    lens_radius: f32,
    focus: f32,
}

impl CameraRays {
    /// Rays for an image of `width × height` (the FOV is kept; the principal point is scaled).
    pub fn new(cam: &Camera, width: u32, height: u32) -> Self {
        let (o, r, u, b) = cam.frame();
        let focal = cam.focal_for_height(height);
        let (cx, cy) = match cam.principal_px {
            Some([px, py]) => (
                px * width as f32 / cam.width as f32,
                py * height as f32 / cam.height as f32,
            ),
            None => (0.5 * width as f32, 0.5 * height as f32),
        };
        CameraRays {
            origin: V3::from_arr(o),
            right: V3::from_arr(r),
            up: V3::from_arr(u),
            forward: -V3::from_arr(b),
            focal,
            cx,
            cy,
            lens_radius: cam.aperture_radius(),
            focus: cam.dof.as_ref().map(|d| d.focus_distance).unwrap_or(1.0),
        }
    }

    /// Whether rays start on a lens ([`CameraRays::ray_lens`]) rather than at a pinhole.
    #[inline(always)]
    pub fn has_lens(&self) -> bool {
        self.lens_radius > 0.0
    }

    /// The thin-lens ray through image point `(px, py)` from the aperture point of uniforms
    /// `(u1, u2)` (see the module docs).
    pub fn ray_lens(&self, px: f32, py: f32, u1: f32, u2: f32) -> Ray {
        let x = (px - self.cx) / self.focal;
        let y = (self.cy - py) / self.focal;
        let in_focus = self.origin + (self.right * x + self.up * y + self.forward) * self.focus;
        let (a, b) = concentric_disk(u1, u2);
        let o = self.origin + self.right * (a * self.lens_radius) + self.up * (b * self.lens_radius);
        Ray::new(o, (in_focus - o).normalize())
    }

    /// The ray through image point `(px, py)` (continuous pixel coordinates).
    pub fn ray(&self, px: f32, py: f32) -> Ray {
        let x = (px - self.cx) / self.focal;
        let y = (self.cy - py) / self.focal;
        let d = (self.right * x + self.up * y + self.forward).normalize();
        Ray::new(self.origin, d)
    }

    /// Distance of `p` along the viewing axis (Cycles' Z pass).
    pub fn z_depth(&self, p: V3) -> f32 {
        (p - self.origin).dot(self.forward)
    }
}
