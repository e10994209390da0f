//! A pinhole camera making world-space primary rays.

use dagfmt::Dag;
use dagfmt::batch::Ray;
use glam::DVec3;

/// A pinhole camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye position (world space).
    pub position: [f64; 3],
    /// Point looked at (world space).
    pub look_at: [f64; 3],
    /// Approximate up direction (made orthogonal to the view direction).
    pub up: [f64; 3],
    /// Vertical field of view in degrees.
    pub fov_y_degrees: f64,
}

/// Why a camera cannot make rays.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// Position and look-at coincide, or a value is not finite.
    #[error("camera position and look-at point must be distinct finite points")]
    Degenerate,
    /// Field of view outside (0, 180) degrees.
    #[error("field of view {0} is not between 0 and 180 degrees")]
    BadFov(f64),
}

/// An orthonormal camera frame ready to make rays.
#[derive(Clone, Copy, Debug)]
pub struct CameraFrame {
    origin: DVec3,
    forward: DVec3,
    right: DVec3,
    up: DVec3,
    /// tan(fov_y / 2).
    tan_half: f64,
}

impl Camera {
    /// A camera that sees the whole root cube (`root_min`, edge `root_size`)
    /// from above one corner, for an image of the given aspect ratio.
    pub fn looking_at_cube(root_min: [f64; 3], root_size: f64, aspect: f64) -> Camera {
        Camera::looking_at_box(root_min, root_min.map(|v| v + root_size), aspect)
    }

    /// The automatic view of a DAG: [`Camera::looking_at_box`] of the box of
    /// its occupied cells (found at a coarse level, so the box may be up to
    /// 1/64 of the cube larger than the voxels), or of the whole cube when the
    /// volume is empty or the file is damaged.
    pub fn automatic(dag: &Dag<'_>, aspect: f64) -> Camera {
        let header = dag.header();
        match occupied_box(dag) {
            Some((lo, hi)) => Camera::looking_at_box(lo, hi, aspect),
            None => Camera::looking_at_cube(header.root_min, header.root_size, aspect),
        }
    }

    /// A camera that sees the whole axis-aligned box `[min, max]` (world
    /// space) from above one corner, for an image of the given aspect ratio.
    pub fn looking_at_box(min: [f64; 3], max: [f64; 3], aspect: f64) -> Camera {
        let (min, max) = (DVec3::from_array(min), DVec3::from_array(max));
        let center = (min + max) * 0.5;
        let fov_y_degrees = 40.0f64;
        let tan_y = (fov_y_degrees.to_radians() * 0.5).tan();
        let tan_x = tan_y * aspect.max(1e-3);
        let direction = DVec3::new(0.9, 0.65, 1.4).normalize();
        let forward = -direction;
        let right = forward.cross(DVec3::Y).normalize();
        let up = right.cross(forward);
        // The nearest distance from the centre at which every corner of the
        // box projects inside the image, plus a small margin.
        let mut distance = 0f64;
        for corner in 0..8 {
            let p = DVec3::new(
                if corner & 1 == 0 { min.x } else { max.x },
                if corner & 2 == 0 { min.y } else { max.y },
                if corner & 4 == 0 { min.z } else { max.z },
            ) - center;
            let needed =
                p.dot(direction) + (p.dot(right).abs() / tan_x).max(p.dot(up).abs() / tan_y);
            distance = distance.max(needed);
        }
        let distance = if distance > 0.0 { distance * 1.05 } else { 1.0 };
        Camera {
            position: (center + direction * distance).to_array(),
            look_at: center.to_array(),
            up: [0.0, 1.0, 0.0],
            fov_y_degrees,
        }
    }

    /// The orthonormal frame of the camera, or why it has none.
    pub fn frame(&self) -> Result<CameraFrame, CameraError> {
        if !(self.fov_y_degrees > 0.0 && self.fov_y_degrees < 180.0) {
            return Err(CameraError::BadFov(self.fov_y_degrees));
        }
        let origin = DVec3::from_array(self.position);
        let target = DVec3::from_array(self.look_at);
        let forward = (target - origin).normalize_or_zero();
        if !origin.is_finite() || !target.is_finite() || forward == DVec3::ZERO {
            return Err(CameraError::Degenerate);
        }
        let mut right = forward
            .cross(DVec3::from_array(self.up))
            .normalize_or_zero();
        if right == DVec3::ZERO {
            // Looking along the up vector: any perpendicular will do.
            right = forward.any_orthonormal_vector();
        }
        let up = right.cross(forward);
        Ok(CameraFrame {
            origin,
            forward,
            right,
            up,
            tan_half: (self.fov_y_degrees.to_radians() * 0.5).tan(),
        })
    }
}

impl CameraFrame {
    /// The ray through the centre of pixel `(x, y)` of a `width` x `height`
    /// image (row 0 at the top), traced over `[0, inf)` at `level`.
    pub fn ray(&self, x: u32, y: u32, width: u32, height: u32, level: Option<u8>) -> Ray {
        self.ray_through(f64::from(x) + 0.5, f64::from(y) + 0.5, width, height, level)
    }

    /// The ray through the image point `(x, y)` (in pixels from the top left
    /// corner; pixel `(i, j)` covers `[i, i + 1) x [j, j + 1)`) of a `width` x
    /// `height` image, traced over `[0, inf)` at `level`.
    pub fn ray_through(&self, x: f64, y: f64, width: u32, height: u32, level: Option<u8>) -> Ray {
        let aspect = f64::from(width) / f64::from(height);
        let u = (x / f64::from(width) * 2.0 - 1.0) * self.tan_half * aspect;
        let v = (1.0 - y / f64::from(height) * 2.0) * self.tan_half;
        let dir = (self.forward + self.right * u + self.up * v).normalize();
        Ray {
            origin: self.origin.as_vec3().to_array(),
            dir: dir.as_vec3().to_array(),
            tmin: 0.0,
            tmax: f32::INFINITY,
            level,
        }
    }

    /// All rays of a `width` x `height` image, row by row from the top.
    pub fn rays(&self, width: u32, height: u32, level: Option<u8>) -> Vec<Ray> {
        (0..height)
            .flat_map(|y| (0..width).map(move |x| self.ray(x, y, width, height, level)))
            .collect()
    }

    /// All rays of a `width` x `height` image in tile order — square tiles
    /// of [`TILE`] x [`TILE`] pixels, tiles row by row from the top, pixels
    /// in Z (Morton) order inside a tile — with the pixel index
    /// (`y * width + x`) of each ray. Neighbouring rays then go in the same
    /// direction, so that the tracer's batch API traces them as packets (see
    /// [`crate::Tracer`]), and each run of 4, 8 or 16 rays of a tile is a
    /// compact block of pixels (2×2, 4×2, 4×4), whose rays meet the same
    /// nodes.
    pub fn rays_in_tiles(
        &self,
        width: u32,
        height: u32,
        level: Option<u8>,
    ) -> (Vec<Ray>, Vec<u32>) {
        let count = width as usize * height as usize;
        let mut rays = Vec::with_capacity(count);
        let mut pixels = Vec::with_capacity(count);
        for ty in (0..height).step_by(TILE as usize) {
            for tx in (0..width).step_by(TILE as usize) {
                for z in 0..TILE * TILE {
                    let (x, y) = (tx + morton_even_bits(z), ty + morton_even_bits(z >> 1));
                    if x < width && y < height {
                        rays.push(self.ray(x, y, width, height, level));
                        pixels.push(y * width + x);
                    }
                }
            }
        }
        (rays, pixels)
    }

    /// The unit view direction.
    pub fn forward(&self) -> [f64; 3] {
        self.forward.to_array()
    }
}

/// The even bits of `z` (a Morton code), packed: the x of pixel `z` of a tile.
pub(crate) fn morton_even_bits(z: u32) -> u32 {
    let mut v = z & 0x5555_5555;
    v = (v | v >> 1) & 0x3333_3333;
    v = (v | v >> 2) & 0x0f0f_0f0f;
    v = (v | v >> 4) & 0x00ff_00ff;
    (v | v >> 8) & 0x0000_ffff
}

/// Edge in pixels of the square tiles of [`CameraFrame::rays_in_tiles`]: 64
/// rays, one packet of the batch API.
pub const TILE: u32 = 8;

/// Level down to which [`occupied_box`] walks the tree: cells of 1/64 of the cube.
const BOX_LEVEL: u8 = 6;

/// World-space box of the occupied cells of level `min(6, leaf level)`, or
/// `None` for an empty volume or a pointer out of bounds. Walks the tree (not
/// the DAG: positions differ), at most 8^6 nodes.
pub fn occupied_box(dag: &Dag<'_>) -> Option<([f64; 3], [f64; 3])> {
    dag.root()?;
    let level = BOX_LEVEL.min(dag.leaf_level());
    let mut lo = [u32::MAX; 3];
    let mut hi = [0u32; 3];
    // (level, word, cell coordinates at that level)
    let mut stack = vec![(0u8, 0u32, [0u32; 3])];
    while let Some((l, word, cell)) = stack.pop() {
        if l == level {
            for i in 0..3 {
                lo[i] = lo[i].min(cell[i]);
                hi[i] = hi[i].max(cell[i] + 1);
            }
            continue;
        }
        let node = dag.node(l, word).ok()?;
        for child in 0..8u32 {
            if let Some(pointer) = node.child_pointer(child) {
                let c = [0, 1, 2].map(|i| cell[i] * 2 + (child >> i & 1));
                stack.push((l + 1, pointer, c));
            }
        }
    }
    let cell = dag.header().root_size / f64::from(1u32 << level);
    let root_min = dag.header().root_min;
    Some((
        [0, 1, 2].map(|i| root_min[i] + f64::from(lo[i]) * cell),
        [0, 1, 2].map(|i| root_min[i] + f64::from(hi[i]) * cell),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_hold_every_pixel_once_in_z_order() {
        let frame = Camera::looking_at_cube([0.0; 3], 1.0, 37.0 / 21.0)
            .frame()
            .expect("a valid camera");
        // Partial tiles at the right and bottom edges too.
        let (width, height) = (37, 21);
        let (rays, pixels) = frame.rays_in_tiles(width, height, Some(3));
        assert_eq!(rays.len(), pixels.len());
        let mut seen = vec![false; (width * height) as usize];
        for (ray, &pixel) in rays.iter().zip(&pixels) {
            assert!(
                !std::mem::replace(&mut seen[pixel as usize], true),
                "pixel {pixel} twice"
            );
            assert_eq!(
                *ray,
                frame.ray(pixel % width, pixel / width, width, height, Some(3))
            );
        }
        assert!(seen.iter().all(|&s| s), "every pixel has its ray");
        // The first full tile: each run of 4 rays is a 2×2 block, of 16 a 4×4.
        let xy = |i: usize| (pixels[i] % width, pixels[i] / width);
        for start in (0..64).step_by(4) {
            let (x0, y0) = xy(start);
            assert_eq!((x0 % 2, y0 % 2), (0, 0));
            let block: Vec<_> = (start..start + 4).map(xy).collect();
            assert_eq!(
                block,
                [(x0, y0), (x0 + 1, y0), (x0, y0 + 1), (x0 + 1, y0 + 1)]
            );
        }
        for start in (0..64).step_by(16) {
            let (x0, y0) = xy(start);
            assert!(
                (start..start + 16)
                    .map(xy)
                    .all(|(x, y)| x / 4 == x0 / 4 && y / 4 == y0 / 4)
            );
        }
    }
}
