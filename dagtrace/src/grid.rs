//! Row-major images of rays, traced in tiles.
//!
//! # Why
//!
//! Packets (module `packet`) are runs of consecutive rays that go nearly the
//! same way. The rays of an image in tile order ([`crate::camera::CameraFrame::rays_in_tiles`])
//! form compact 8×8-pixel packets, but the same image row by row, the order
//! most programs make rays in, forms 64×1 strips: beams 64 times wider than
//! they are tall, which meet many more cells for the same rays (on dragon at
//! depth 12, row-order frames took 1.6 times the instructions of tiled ones).
//! So the batch API recognises a row-major image at the start of a run of
//! rays from one origin and traces it tile by tile, gathering each tile's
//! rays into a packet of its own.
//!
//! # How
//!
//! [`find_grid`] looks for the end of the first row: the first ray where the
//! step between neighbouring directions changes abruptly (the jump back to
//! the left edge), after a run of steps that change smoothly. The rows must
//! be at least [`MIN_WIDTH`] rays long, the ray below the first ray must be
//! about as close to it as its right neighbour is, and the first and last
//! rays of every row must start like the first ray (origin, bounds and level
//! bit for bit). Nothing of the answers depends on this being right: a
//! gathered tile whose rays do not make a packet is traced ray by ray, so a
//! wrong guess costs time, never correctness. Then [`tiles`] lists the 8×8
//! tiles of the image strip by strip, each tile's pixels in Z order (4×4
//! blocks first, like the groups of a packet).

use dagfmt::batch::Ray;

/// Fewest rays in a row of an image worth tiling.
pub(crate) const MIN_WIDTH: usize = 16;

/// Most rays in a row looked for.
const MAX_WIDTH: usize = 1 << 16;

/// Edge of a tile in rays (a packet of 64).
pub(crate) const TILE: usize = 8;

/// A row-major image of rays at the start of a slice: `rows` rows of
/// `width` rays.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct ImageGrid {
    pub(crate) width: usize,
    pub(crate) rows: usize,
}

impl ImageGrid {
    /// Rays in the image.
    pub(crate) fn len(&self) -> usize {
        self.width * self.rows
    }
}

/// Whether `a` starts like `b`: the same origin, bounds and level, bit for bit.
#[inline(always)]
pub(crate) fn same_start(a: &Ray, b: &Ray) -> bool {
    let bits = |r: &Ray| [r.origin[0], r.origin[1], r.origin[2], r.tmin, r.tmax].map(f32::to_bits);
    bits(a) == bits(b) && a.level == b.level
}

/// Largest absolute component.
#[inline(always)]
fn norm(v: [f32; 3]) -> f32 {
    v[0].abs().max(v[1].abs()).max(v[2].abs())
}

#[inline(always)]
fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// The row-major image at the start of `rays` (see the module docs), if
/// there is one of at least [`MIN_WIDTH`] × [`TILE`] rays.
pub(crate) fn find_grid(rays: &[Ray]) -> Option<ImageGrid> {
    let first = rays.first()?;
    if rays.len() < MIN_WIDTH * TILE {
        return None;
    }
    let step = sub(rays[1].dir, first.dir);
    // Written so that a NaN fails.
    let moves = norm(step) > 0.0;
    if !moves || !same_start(&rays[1], first) {
        return None;
    }
    // The first row: steps that change smoothly, then a jump.
    let mut previous = step;
    let mut width = None;
    for j in 1..(rays.len() - 1).min(MAX_WIDTH) {
        let next = &rays[j + 1];
        let d = sub(next.dir, rays[j].dir);
        // A NaN is a jump.
        let smooth = norm(sub(d, previous)) <= 0.5 * norm(previous);
        if !smooth || !same_start(next, first) {
            width = Some(j + 1);
            break;
        }
        previous = d;
    }
    let width = width?;
    if width < MIN_WIDTH || rays.len() < width * TILE {
        return None;
    }
    // The ray below the first: about as close as its right neighbour.
    let down = norm(sub(rays[width].dir, first.dir));
    let square = down <= 4.0 * norm(step) && down * 4.0 >= norm(step);
    if !square {
        return None;
    }
    let mut rows = 1;
    while (rows + 1) * width <= rays.len() {
        let (start, end) = (&rays[rows * width], &rays[rows * width + width - 1]);
        if !same_start(start, first) || !same_start(end, first) {
            break;
        }
        rows += 1;
    }
    (rows >= TILE).then_some(ImageGrid { width, rows })
}

/// The x of pixel `z` of a tile in Z (Morton) order: the even bits of `z`.
#[inline(always)]
fn morton_x(z: usize) -> usize {
    (z & 1) | (z >> 1 & 2) | (z >> 2 & 4)
}

/// Calls `tile` with the ray indices of every tile of `grid`, strip by strip
/// (8 rows at a time) and left to right in a strip, each tile's pixels in Z
/// order; tiles at the right and bottom edges hold the pixels that exist.
pub(crate) fn tiles(grid: ImageGrid, mut tile: impl FnMut(&[usize])) {
    let mut indices = [0usize; TILE * TILE];
    for y0 in (0..grid.rows).step_by(TILE) {
        for x0 in (0..grid.width).step_by(TILE) {
            let mut n = 0;
            for z in 0..TILE * TILE {
                let (x, y) = (x0 + morton_x(z), y0 + morton_x(z >> 1));
                if x < grid.width && y < grid.rows {
                    indices[n] = y * grid.width + x;
                    n += 1;
                }
            }
            tile(&indices[..n]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;

    fn camera_rays(width: u32, height: u32) -> Vec<Ray> {
        Camera {
            position: [3.0, 2.0, 4.0],
            look_at: [0.5, 0.5, 0.5],
            up: [0.0, 1.0, 0.0],
            fov_y_degrees: 50.0,
        }
        .frame()
        .unwrap()
        .rays(width, height, None)
    }

    #[test]
    fn row_major_images_are_found() {
        for (w, h) in [(16, 8), (17, 9), (640, 480), (960, 540), (33, 100)] {
            let rays = camera_rays(w, h);
            assert_eq!(
                find_grid(&rays),
                Some(ImageGrid {
                    width: w as usize,
                    rows: h as usize
                }),
                "{w}x{h}"
            );
            // Followed by other rays: the image ends where they begin.
            let mut more = rays.clone();
            more.extend(camera_rays(w + 3, h).iter().map(|r| Ray {
                origin: [9.0; 3],
                ..*r
            }));
            assert_eq!(find_grid(&more).map(|g| g.len()), Some(rays.len()));
        }
    }

    #[test]
    fn other_orders_are_not_images() {
        // Too narrow, too few rows.
        assert_eq!(find_grid(&camera_rays(15, 100)), None);
        assert_eq!(find_grid(&camera_rays(100, 7)), None);
        // Tile order.
        let frame = Camera::looking_at_cube([0.0; 3], 1.0, 1.5).frame().unwrap();
        let (tiled, _) = frame.rays_in_tiles(320, 200, None);
        assert_eq!(find_grid(&tiled), None);
        // Columns rather than rows: the image's transpose, rows of 100.
        let rays = camera_rays(40, 100);
        let columns: Vec<Ray> = (0..40)
            .flat_map(|x| (0..100).map(move |y| (x, y)))
            .map(|(x, y)| rays[y * 40 + x])
            .collect();
        assert_eq!(find_grid(&columns).map(|g| g.width), Some(100));
        // Random directions from one origin.
        let mut state = 7u32;
        let mut unit = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1 << 24) as f32 - 0.5
        };
        let random: Vec<Ray> = (0..5000)
            .map(|_| Ray {
                dir: [unit(), unit(), unit()],
                ..rays[0]
            })
            .collect();
        assert_eq!(find_grid(&random), None);
        // A different origin in the first row.
        let mut broken = camera_rays(64, 64);
        broken[20].origin[0] += 1.0;
        assert_eq!(find_grid(&broken), None);
    }

    #[test]
    fn tiles_cover_every_pixel_once_in_z_order() {
        for (w, h) in [(16, 8), (17, 9), (64, 70)] {
            let grid = ImageGrid { width: w, rows: h };
            let mut seen = vec![0u32; w * h];
            let mut tiles_seen = 0;
            tiles(grid, |t| {
                tiles_seen += 1;
                for &i in t {
                    seen[i] += 1;
                }
                // A full tile: its first 16 pixels are the top-left 4×4 block.
                if t.len() == 64 {
                    let (x0, y0) = (t[0] % w, t[0] / w);
                    for &i in &t[..16] {
                        assert!(i % w - x0 < 4 && i / w - y0 < 4);
                    }
                }
            });
            assert!(seen.iter().all(|&n| n == 1), "{w}x{h}");
            assert_eq!(tiles_seen, w.div_ceil(8) * h.div_ceil(8));
        }
    }
}
