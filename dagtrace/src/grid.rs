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
//! wrong guess costs time, never correctness. Then [`tiles`] lists the
//! 8×8 tiles of the image, each tile as runs of consecutive rays (its 4×4
//! blocks, the groups of a packet, row by row), copied into a packet of
//! their own.

use dagfmt::batch::Ray;

/// Fewest rays in a row of an image worth tiling.
pub(crate) const MIN_WIDTH: usize = 16;

/// Most rays in a row looked for.
const MAX_WIDTH: usize = 1 << 16;

/// Rows of an image worth tiling, and of the strips its rays are traced
/// in on all cores (one row of tiles).
pub(crate) const TILE: usize = 8;

/// Width and height of a tile in rays (a packet of 64). 8×8: its beams are
/// the narrowest, for the fewest instructions. (16×4 tiles, four rows of
/// the image gathered at a time, had taken 3–5 % less time before the next
/// tile's rows were prefetched; with the prefetch, 8×8 took 0.95–0.98 of
/// 16×4's time on a Zen 4 EPYC: dagtrace/BENCHMARKS.md.)
pub(crate) const TILE_WIDTH: usize = 8;
/// See [`TILE_WIDTH`].
pub(crate) const TILE_HEIGHT: usize = 8;

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

/// The rays looked at by [`images`] for the start of an image are
/// `IMAGE_STRIDE_MIN` apart at first and after each image, twice as far
/// apart after each look that starts none, up to `IMAGE_STRIDE_MAX`. One
/// thread looks while the others wait: looking at every 64th ray of a
/// 1920×1080 batch in tile order (32,400 reads from memory, half of them on
/// a new page, none starting an image) took 1.3–1.6 ms, 4 % of the batch's
/// time on two cores (machine C, dagtrace/BENCHMARKS.md); now it looks at
/// about 2,000 rays.
const IMAGE_STRIDE_MIN: usize = 64;
/// See [`IMAGE_STRIDE_MIN`].
const IMAGE_STRIDE_MAX: usize = 1024;

/// The row-major images in a batch of rays, in order: (first ray, grid).
/// Images start where a run of rays with one start begins: a ray looked at
/// (see [`IMAGE_STRIDE_MIN`]) that starts differently from the last one
/// looked at, and like the ray [`MIN_WIDTH`] × [`TILE`] − 1 further on, is
/// followed back to the first ray of its run, and [`find_grid`] tried
/// there; after an image, the next is tried right where it ends. So every
/// image is found that follows another, or that starts differently from the
/// rays before it and holds at least `IMAGE_STRIDE_MAX` + 128 rays (any
/// image of 1,152 rays or more); a smaller one may be missed, and then its rays
/// are traced as other rays are (the same answers).
pub(crate) fn images(rays: &[Ray]) -> Images<'_> {
    Images {
        rays,
        at: 0,
        done: 0,
        previous: None,
        stride: IMAGE_STRIDE_MIN,
        looked: 0,
    }
}

/// The iterator of [`images`].
#[derive(Clone, Debug)]
pub(crate) struct Images<'a> {
    rays: &'a [Ray],
    /// The next ray to look at.
    at: usize,
    /// The end of the last image found: the look goes back no further.
    done: usize,
    /// The last ray looked at, unless an image ended since.
    previous: Option<usize>,
    stride: usize,
    /// Rays looked at so far.
    pub(crate) looked: usize,
}

impl Iterator for Images<'_> {
    type Item = (usize, ImageGrid);

    fn next(&mut self) -> Option<(usize, ImageGrid)> {
        const SMALLEST: usize = MIN_WIDTH * TILE;
        let rays = self.rays;
        while self.at < rays.len() {
            let i = self.at;
            self.looked += 1;
            let changed = self
                .previous
                .is_none_or(|p| !same_start(&rays[i], &rays[p]));
            if changed
                && i + SMALLEST <= rays.len()
                && same_start(&rays[i], &rays[i + SMALLEST - 1])
            {
                let mut start = i;
                while start > self.done && same_start(&rays[start - 1], &rays[i]) {
                    start -= 1;
                }
                if let Some(image) = find_grid(&rays[start..]) {
                    let end = start + image.len();
                    self.done = end;
                    self.at = end;
                    self.previous = None;
                    self.stride = IMAGE_STRIDE_MIN;
                    return Some((start, image));
                }
            }
            self.previous = Some(i);
            self.at = i + self.stride;
            self.stride = (self.stride * 2).min(IMAGE_STRIDE_MAX);
        }
        None
    }
}

/// Edge of the blocks of a tile: a packet's groups of 16 rays.
const BLOCK: usize = 4;

/// Runs of [`BLOCK`] rays in a tile.
const TILE_RUNS: usize = TILE_WIDTH * TILE_HEIGHT / BLOCK;

/// The [`TILE_WIDTH`]×[`TILE_HEIGHT`] tiles of `grid`, a row of tiles at a
/// time and left to right. Each tile's rays are [`Tile::runs`]: the tile's
/// columns of 4×4 blocks left to right, each column row by row, so that
/// every 16 rays of a full tile are one block (a group of its packet). Tiles
/// at the right and bottom edges hold the rays that exist.
pub(crate) fn tiles(grid: ImageGrid) -> Tiles {
    Tiles { grid, x0: 0, y0: 0 }
}

/// The iterator of [`tiles`].
#[derive(Clone, Debug)]
pub(crate) struct Tiles {
    grid: ImageGrid,
    x0: usize,
    y0: usize,
}

/// One tile of [`tiles`]: its top left pixel.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Tile {
    grid: ImageGrid,
    x0: usize,
    y0: usize,
}

/// The rays of a tile as runs of consecutive rays (first index, length):
/// `runs[..len]`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct TileRuns {
    pub(crate) runs: [(usize, usize); TILE_RUNS],
    pub(crate) len: usize,
}

impl TileRuns {
    /// No rays.
    const EMPTY: TileRuns = TileRuns {
        runs: [(0, 0); TILE_RUNS],
        len: 0,
    };
}

impl Tile {
    /// Whether the tile has all its rays (not cut by an edge).
    #[inline(always)]
    pub(crate) fn is_full(&self) -> bool {
        self.x0 + TILE_WIDTH <= self.grid.width && self.y0 + TILE_HEIGHT <= self.grid.rows
    }

    /// Calls `f(n, i)` for the 16 runs of `BLOCK` rays of a full tile, in
    /// packet order (column of blocks by column, left to right, each column
    /// row by row):
    /// `n` the run's first ray in the packet, `i` in the image.
    #[inline(always)]
    pub(crate) fn for_each_block_row(&self, mut f: impl FnMut(usize, usize)) {
        for b in 0..TILE_WIDTH / BLOCK {
            for y in 0..TILE_HEIGHT {
                let i = (self.y0 + y) * self.grid.width + self.x0 + b * BLOCK;
                f((b * TILE_HEIGHT + y) * BLOCK, i);
            }
        }
    }

    /// The tile's rays, column of blocks by column, each column row by row.
    pub(crate) fn runs(&self) -> TileRuns {
        let (grid, x0, y0) = (self.grid, self.x0, self.y0);
        let mut tile = TileRuns::EMPTY;
        for bx in (x0..(x0 + TILE_WIDTH).min(grid.width)).step_by(BLOCK) {
            let len = BLOCK.min(grid.width - bx);
            for y in y0..(y0 + TILE_HEIGHT).min(grid.rows) {
                tile.runs[tile.len & (TILE_RUNS - 1)] = (y * grid.width + bx, len);
                tile.len += 1;
            }
        }
        tile
    }
}

impl Iterator for Tiles {
    type Item = Tile;

    #[inline(always)]
    fn next(&mut self) -> Option<Tile> {
        let grid = self.grid;
        if self.y0 >= grid.rows || grid.width == 0 {
            return None;
        }
        let (x0, y0) = (self.x0, self.y0);
        self.x0 += TILE_WIDTH;
        if self.x0 >= grid.width {
            self.x0 = 0;
            self.y0 += TILE_HEIGHT;
        }
        Some(Tile { grid, x0, y0 })
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

    /// Rays that each start elsewhere: no image among them.
    fn scattered_rays(count: usize) -> Vec<Ray> {
        let rays = camera_rays(100, count.div_ceil(100) as u32);
        rays[..count]
            .iter()
            .enumerate()
            .map(|(i, r)| Ray {
                origin: [9.0 + i as f32 * 1e-3, 1.0, 2.0],
                ..*r
            })
            .collect()
    }

    #[test]
    fn images_are_found_among_other_rays() {
        let other_camera = Camera {
            position: [-2.0, 1.0, -3.0],
            look_at: [0.5, 0.4, 0.5],
            up: [0.0, 1.0, 0.0],
            fov_y_degrees: 40.0,
        }
        .frame()
        .unwrap()
        .rays(160, 120, None);
        // Each part of the batch, with the (width, rows) of the image it is.
        type Part = (Vec<Ray>, Option<(usize, usize)>);
        let parts: [Part; 6] = [
            (scattered_rays(3000), None),
            (camera_rays(48, 40), Some((48, 40))),
            (scattered_rays(2500), None),
            (camera_rays(640, 480), Some((640, 480))),
            // Right after the last image, from another camera.
            (other_camera, Some((160, 120))),
            (scattered_rays(777), None),
        ];
        let mut rays = Vec::new();
        let mut expected = Vec::new();
        for (part, image) in &parts {
            if let Some((width, rows)) = *image {
                expected.push((rays.len(), ImageGrid { width, rows }));
            }
            rays.extend_from_slice(part);
        }
        assert_eq!(images(&rays).collect::<Vec<_>>(), expected);
        // No images: nothing found, and the look thins out.
        assert_no_image_found_sparsely(&scattered_rays(200_000));
    }

    /// `rays` hold no image, and the search for one reads at most about one
    /// ray in `IMAGE_STRIDE_MAX`.
    fn assert_no_image_found_sparsely(rays: &[Ray]) {
        let mut search = images(rays);
        assert_eq!(search.next(), None);
        assert!(
            search.looked <= rays.len() / IMAGE_STRIDE_MAX + 8,
            "{} rays looked at",
            search.looked
        );
    }

    #[test]
    fn tile_order_is_searched_sparsely() {
        // 1920×1080 in tile order: one origin, no row-major image; the look
        // must not read every 64th ray of it (see IMAGE_STRIDE_MIN).
        let frame = Camera::looking_at_cube([0.0; 3], 1.0, 1.5).frame().unwrap();
        let (tiled, _) = frame.rays_in_tiles(1920, 1080, None);
        assert_no_image_found_sparsely(&tiled);
    }

    #[test]
    fn tiles_cover_every_pixel_once_in_blocks() {
        for (w, h) in [(16, 8), (17, 9), (64, 70), (6, 3)] {
            let grid = ImageGrid { width: w, rows: h };
            let mut seen = vec![0u32; w * h];
            let mut tiles_seen = 0;
            for tile in tiles(grid) {
                let tile_runs = tile.runs();
                let runs = &tile_runs.runs[..tile_runs.len];
                tiles_seen += 1;
                let rays: Vec<usize> = runs.iter().flat_map(|&(i, n)| i..i + n).collect();
                for &i in &rays {
                    seen[i] += 1;
                }
                // Each tile within its pixels; in a full tile, each 16 rays
                // are a 4×4 block.
                let (x0, y0) = (rays[0] % w, rays[0] / w);
                assert!(
                    rays.iter()
                        .all(|&i| i % w - x0 < TILE_WIDTH && i / w - y0 < TILE_HEIGHT)
                );
                assert_eq!(tile.is_full(), rays.len() == 64);
                if tile.is_full() {
                    // The blocks' rows as `for_each_block_row` gives them.
                    let mut rows = Vec::new();
                    tile.for_each_block_row(|n, i| rows.extend((0..4).map(|k| (n + k, i + k))));
                    assert_eq!(rows, rays.iter().copied().enumerate().collect::<Vec<_>>());
                    for block in rays.chunks(16) {
                        let (bx, by) = (block[0] % w, block[0] / w);
                        assert!(block.iter().all(|&i| i % w - bx < 4 && i / w - by < 4));
                    }
                }
            }
            assert!(seen.iter().all(|&n| n == 1), "{w}x{h}");
            assert_eq!(tiles_seen, w.div_ceil(TILE_WIDTH) * h.div_ceil(TILE_HEIGHT));
        }
    }
}
