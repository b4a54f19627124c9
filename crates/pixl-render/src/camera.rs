//! Pinhole camera rays (box pixel filter: uniform jitter inside the pixel). Pixel `(x, y)` has
//! its top-left corner at `(x, y)`; row 0 is the top of the image. The camera looks down −Z.
use crate::bvh::Ray;
use crate::math::V3;
use crate::scene::Camera;

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
        }
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
