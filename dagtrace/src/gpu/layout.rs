//! The records and constants the host and the shader share.
//!
//! This module is the single source of truth: the WGSL declarations of the
//! structs, the constants and the resource bindings are generated from the Rust
//! definitions below and prepended to `trace.wgsl` ([`preamble`]). A unit test
//! parses the generated shader with naga and checks that every member of every
//! shared struct has the offset and size the Rust `#[repr(C)]` struct gives it.

use bytemuck::{Pod, Zeroable};
use dagfmt::layout::{CHILD_MASK_BITS, COUNT_SATURATED, MAX_DEPTH};
use std::fmt::Write as _;

/// Level sections a file can have: levels `0 ..= MAX_DEPTH - 2`.
pub const MAX_STORED_LEVELS: usize = MAX_DEPTH as usize - 1;

/// Invocations per workgroup of the batch entry point (one ray each).
pub const BATCH_WORKGROUP_SIZE: u32 = 64;
/// Edge of the square pixel tile of one render workgroup.
pub const RENDER_TILE: u32 = 8;

/// `GpuHit::info` bit: the ray hit an occupied cell.
pub const INFO_HIT: u32 = 1;
/// `GpuHit::info` bit: the ray ran out of iterations (see `GpuOptions::max_iterations`).
pub const INFO_EXHAUSTED: u32 = 2;
/// `GpuHit::info` bit: a child pointer led outside its level (malformed file).
pub const INFO_MALFORMED: u32 = 4;
/// `GpuHit::info` bits `8..16`: the level of the hit cell.
pub const INFO_LEVEL_SHIFT: u32 = 8;
/// `GpuHit::info` bits `16..24`: the entry face.
pub const INFO_FACE_SHIFT: u32 = 16;

/// `GpuRay::flags` bit: the host already answered this ray; the shader writes a miss.
pub const RAY_SKIP: u32 = 1;
/// `GpuRay::flags` bit: the host computes this ray's entry parameter and face
/// (rare rays: no direction, a far origin, an extreme scale); the shader
/// only finds the cell. Echoed in `GpuHit::cell.w` as [`INFO_HOST_ANSWER`].
pub const RAY_HOST_ANSWER: u32 = 2;
/// `GpuRay::flags` bits `4..7`: the axes whose direction is not (treated as)
/// zero, which alone decide the entry face (bit `4 + i` for axis `i`).
pub const RAY_MOVING_SHIFT: u32 = 4;
/// `GpuHit::cell.w` bit (batch): the ray was flagged [`RAY_SKIP`] (answered
/// on the host); nothing else in the record is meaningful.
pub const INFO_SKIPPED: u32 = 16;
/// `GpuHit::cell.w` bit (batch): the host must compute `t` and the face (the
/// ray was flagged [`RAY_HOST_ANSWER`], or it starts inside the cell it hits).
pub const INFO_HOST_ANSWER: u32 = 8;
/// Largest magnitude of `GpuRay::scale_exponent` the shader answers itself:
/// `t * 2^-k` is then exact in f32 for every `t` the traversal produces.
pub const MAX_SHADER_SCALE_EXPONENT: i32 = 64;
/// Bound given to infinite parameter bounds (`tmin = -inf`, `tmax = inf`)
/// in the shader: beyond every plane parameter of a ray whose origin lies
/// within 16 cube sizes (at most 2^86), so the traversal is the same.
pub const PARAMETER_BOUND: f32 = 1.0e30;

/// `GpuParams::options` bit: compute the dense attribute index of hits.
pub const OPTION_INDEX: u32 = 1;
/// `GpuParams::options` bit (render): write `GpuHit` records.
pub const OPTION_WRITE_HITS: u32 = 2;
/// `GpuParams::options` bit (render): write RGBA8 pixels.
pub const OPTION_WRITE_IMAGE: u32 = 4;

/// Face code of a ray that starts inside the cell; faces `1 + 2 * axis + negative`
/// follow (1 = -X, 2 = +X, 3 = -Y, 4 = +Y, 5 = -Z, 6 = +Z).
pub const FACE_INSIDE: u32 = 0;

/// Inverse direction given to axes whose direction is (treated as) zero: the
/// CPU tracer's `1 / 2^-60`, so both traversals treat such axes alike.
pub const TINY_DIRECTION_INVERSE: f32 = (1u64 << 60) as f32;
/// Far end of camera rays, in grid units along a unit direction.
pub const RENDER_FAR: f32 = 1.0e30;

/// Invocations per workgroup of the colour pass (one record each).
pub const COLOR_WORKGROUP_SIZE: u32 = 64;
/// Workgroups per row of a colour dispatch (rows of them cover more records).
pub const COLOR_DISPATCH_ROW: u32 = 32768;
/// Bind group of the colour pass (its own pipeline layout: no DAG pages).
pub const GROUP_COLORS: u32 = 0;
/// Binding of [`GpuColorParams`] in [`GROUP_COLORS`].
pub const BINDING_COLOR_PARAMS: u32 = 0;
/// Binding of the records (hits, surfaces, indices) in [`GROUP_COLORS`].
pub const BINDING_COLOR_RECORDS: u32 = 1;
/// Binding of the output in [`GROUP_COLORS`]: two words a record, the RGBA8
/// colour (R in the low byte) and 1 when the record got one.
pub const BINDING_COLOR_OUT: u32 = 2;
/// First binding of the colour section's pages in [`GROUP_COLORS`].
pub const BINDING_COLOR_PAGES: u32 = 3;
/// Storage buffers of the colour pass besides its pages.
pub const COLOR_IO_STORAGE_BUFFERS: u32 = 2;

/// Marks "not replaying a path" in the short-stack traversal.
pub const NO_REPLAY: u32 = u32::MAX;

/// Bind group 0 (per dispatch): parameters, rays, hits, image.
pub const GROUP_IO: u32 = 0;
/// Bind group 1 (per DAG): the pages of the DAG's words.
pub const GROUP_PAGES: u32 = 1;
/// Binding of [`GpuParams`] in [`GROUP_IO`].
pub const BINDING_PARAMS: u32 = 0;
/// Binding of the `GpuRay` array in [`GROUP_IO`].
pub const BINDING_RAYS: u32 = 1;
/// Binding of the `GpuHit` array in [`GROUP_IO`].
pub const BINDING_HITS: u32 = 2;
/// Binding of the RGBA8 image (one `u32` per pixel) in [`GROUP_IO`].
pub const BINDING_IMAGE: u32 = 3;
/// Storage buffers of [`GROUP_IO`]; the pages get what the adapter allows beyond these.
pub const IO_STORAGE_BUFFERS: u32 = 3;
/// Most page bindings the shader is generated with.
pub const MAX_PAGES: u32 = 16;

/// A Rust type with a WGSL spelling of the same size and alignment.
pub(crate) trait WgslType {
    /// The WGSL type.
    fn wgsl() -> String;
}

impl WgslType for u32 {
    fn wgsl() -> String {
        "u32".into()
    }
}

impl WgslType for f32 {
    fn wgsl() -> String {
        "f32".into()
    }
}

impl WgslType for [f32; 4] {
    fn wgsl() -> String {
        "vec4<f32>".into()
    }
}

impl WgslType for [u32; 4] {
    fn wgsl() -> String {
        "vec4<u32>".into()
    }
}

impl<const N: usize> WgslType for [[u32; 4]; N] {
    fn wgsl() -> String {
        format!("array<vec4<u32>, {N}>")
    }
}

/// Where a member of a shared struct lies, as Rust lays it out.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct FieldLayout {
    pub name: &'static str,
    pub wgsl: String,
    pub offset: usize,
    pub size: usize,
}

/// A `#[repr(C)]` struct with a WGSL twin.
pub(crate) trait GpuStruct: Pod {
    /// Name of the struct in WGSL (the same as in Rust).
    const NAME: &'static str;
    /// Members in declaration order.
    fn fields() -> Vec<FieldLayout>;

    /// The WGSL declaration.
    fn wgsl_declaration() -> String {
        let mut s = format!("struct {} {{\n", Self::NAME);
        for f in Self::fields() {
            let _ = writeln!(s, "    {}: {},", f.name, f.wgsl);
        }
        s.push_str("}\n");
        s
    }
}

/// Declares a `#[repr(C)]` Pod struct and its [`GpuStruct`] description.
macro_rules! gpu_struct {
    ($(#[$meta:meta])* pub struct $name:ident { $($(#[$fmeta:meta])* pub $field:ident : $ty:ty,)* }) => {
        $(#[$meta])*
        #[repr(C)]
        #[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
        pub struct $name {
            $($(#[$fmeta])* pub $field: $ty,)*
        }

        impl GpuStruct for $name {
            const NAME: &'static str = stringify!($name);
            fn fields() -> Vec<FieldLayout> {
                vec![$(FieldLayout {
                    name: stringify!($field),
                    wgsl: <$ty as WgslType>::wgsl(),
                    offset: std::mem::offset_of!($name, $field),
                    size: size_of::<$ty>(),
                },)*]
            }
        }
    };
}

/// The lit renderer (`lit.rs`) declares its records with it too.
pub(crate) use gpu_struct;

gpu_struct! {
    /// A ray prepared for the traversal: grid space, mirrored so that every
    /// direction component is non-negative, scaled and re-based exactly as the
    /// CPU tracer does (see `prepare.rs`).
    pub struct GpuRay {
        /// Mirrored origin (xyz); `w` = start of the parameter interval.
        pub origin: [f32; 4],
        /// Inverse of the mirrored direction (xyz, all positive); `w` = end of
        /// the parameter interval.
        pub inv_dir: [f32; 4],
        /// Bit `i` set when axis `i` is mirrored (the direction was negative).
        pub octant: u32,
        /// Level of detail traced (1 ..= depth).
        pub level: u32,
        /// [`RAY_SKIP`], [`RAY_HOST_ANSWER`], the moving axes
        /// ([`RAY_MOVING_SHIFT`]).
        pub flags: u32,
        /// `k` (an `i32`'s bits) of the power of two `2^k` the direction was
        /// scaled by: the shader reports `t * 2^-k`, the parameter of the
        /// ray as given (the CPU tracer's `t * inv_scale`).
        pub scale_exponent: u32,
    }
}

gpu_struct! {
    /// The shader's answer for one ray.
    pub struct GpuHit {
        /// Cell coordinates at the hit level (xyz, file frame); `w` = info bits
        /// ([`INFO_HIT`], [`INFO_EXHAUSTED`], [`INFO_MALFORMED`], level, face).
        pub cell: [u32; 4],
        /// Entry parameter (batch: of the ray as given, unless
        /// [`INFO_HOST_ANSWER`]; render: world units along the view ray).
        pub t: f32,
        /// Low 32 bits of the dense attribute index.
        pub index_lo: u32,
        /// High 32 bits of the dense attribute index.
        pub index_hi: u32,
        /// Loop iterations the traversal took (for statistics).
        pub iterations: u32,
    }
}

gpu_struct! {
    /// Per-DAG and per-dispatch parameters (a uniform buffer).
    pub struct GpuParams {
        /// Depth D.
        pub depth: u32,
        /// D - 2.
        pub leaf_level: u32,
        /// Rays in this dispatch (batch) or pixels (render).
        pub ray_count: u32,
        /// Loop iterations after which a ray gives up ([`INFO_EXHAUSTED`]).
        pub max_iterations: u32,
        /// Word address of the saturated-count table: `(address, low, high)` triples.
        pub sat_base: u32,
        /// Entries in the saturated-count table.
        pub sat_count: u32,
        /// [`OPTION_INDEX`], [`OPTION_WRITE_HITS`], [`OPTION_WRITE_IMAGE`].
        pub options: u32,
        /// Level of detail of camera rays.
        pub render_level: u32,
        /// Image width in pixels (render).
        pub width: u32,
        /// Image height in pixels (render).
        pub height: u32,
        /// 1 when the volume is empty.
        pub empty: u32,
        /// Zero.
        pub pad0: u32,
        /// Camera origin in grid space (xyz); `w` = world units per grid unit.
        pub cam_origin: [f32; 4],
        /// Unit view direction in grid space.
        pub cam_forward: [f32; 4],
        /// Right vector scaled by tan(fov/2) * aspect.
        pub cam_right: [f32; 4],
        /// Up vector scaled by tan(fov/2).
        pub cam_up: [f32; 4],
        /// Per level: word address of the section; the reference widths
        /// (1.0: pointer bytes; 2.0 in place: the bit widths `w1 | w2 << 8 |
        /// w3 << 16`, spec §23.2, 0 for the leaf level; 2.0 expanded: 4);
        /// units (1.0 and 2.0 expanded: words; 2.0 in place: bytes; leaves
        /// for the leaf level), the bound a child address must be below;
        /// 2.0 in place: the word address of the level's record-start bit
        /// vector (`upload::record_starts`), 0 when it has none.
        pub levels: [[u32; 4]; MAX_STORED_LEVELS],
    }
}

gpu_struct! {
    /// Parameters of the colour pass (`colors.wgsl`, a uniform buffer): which
    /// records to decode the colours of, and how the file's colour section
    /// is laid out.
    pub struct GpuColorParams {
        /// Records in this dispatch.
        pub count: u32,
        /// Words per record.
        pub stride: u32,
        /// Word of a record holding its info bits (see `info_mask`).
        pub info_word: u32,
        /// Word of a record holding the low 32 bits of the attribute index
        /// (the high 32 bits follow).
        pub index_word: u32,
        /// A record is looked up only when `info & info_mask == info_mask`
        /// (0: every record).
        pub info_mask: u32,
        /// Colours in the section (N, the file's voxel count; below 2^32).
        pub colors: u32,
        /// Packed sections: the trailer's error bound E.
        pub error_bound: u32,
        /// Packed sections: the block shift S (6, 7 or 8).
        pub block_shift: u32,
        /// Packed sections: 1 when palette blocks carry split flags.
        pub split: u32,
        /// Packed sections: bits O of a block's offset in a directory entry.
        pub offset_bits: u32,
        /// Packed sections: byte offset of the directory in the section.
        pub directory: u32,
        /// Zero.
        pub pad0: u32,
    }
}

const _: () = assert!(size_of::<GpuRay>() == 48);
const _: () = assert!(size_of::<GpuHit>() == 32);
const _: () = assert!(size_of::<GpuParams>() == 48 + 64 + 16 * MAX_STORED_LEVELS);
const _: () = assert!(size_of::<GpuParams>().is_multiple_of(16));
const _: () = assert!(size_of::<GpuColorParams>() == 48);

/// How the shader is specialised: fixed per pipeline.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(crate) struct ShaderConfig {
    /// Entries of the traversal stack (a power of two when short).
    pub stack_size: u32,
    /// Whether the stack is short (a ring that restarts from the root).
    pub short_stack: bool,
    /// Storage bindings holding the DAG's words.
    pub pages: u32,
    /// log2 of the words per page (when there is more than one page).
    pub page_shift: u32,
    /// Whether the DAG is format 2.0 (spec §23): the shader is compiled with
    /// `FORMAT_V2 = true`, its 2.0 decoder and the accumulated reflections;
    /// a 1.0 shader has them compiled out (constant-false branches).
    pub format_v2: bool,
    /// With `format_v2`: whether the node levels are uploaded expanded
    /// (`dagfmt::expand`, spec §23.12: 1.0-like records of aligned words,
    /// a child one word `index << 3 | r`), so that the shader reads a child
    /// with one load, as in 1.0, and keeps only the reflections of the 2.0
    /// variant; else it decodes the records in place (`V2_IN_PLACE`).
    /// Ignored without `format_v2`.
    pub expanded: bool,
}

impl ShaderConfig {
    /// Whether the shader decodes 2.0 records in place (bit streams at
    /// byte offsets, spec §23.2) rather than reading aligned words.
    pub fn v2_in_place(&self) -> bool {
        self.format_v2 && !self.expanded
    }
}

fn constant_u32(s: &mut String, name: &str, value: u32) {
    let _ = writeln!(s, "const {name}: u32 = {value}u;");
}

fn constant_f32(s: &mut String, name: &str, value: f32) {
    // `{:?}` prints the shortest representation that reads back exactly; WGSL
    // accepts the exponent form.
    let _ = writeln!(s, "const {name}: f32 = {value:?};");
}

/// The generated WGSL that precedes `trace.wgsl`: shared constants, structs,
/// bindings and the page-switching word loader.
pub(crate) fn preamble(config: &ShaderConfig) -> String {
    let mut s = String::from(
        "// Generated by dagtrace::gpu::layout from the Rust definitions. Do not edit.\n\n",
    );
    constant_u32(&mut s, "MAX_STORED_LEVELS", MAX_STORED_LEVELS as u32);
    constant_u32(&mut s, "BATCH_WORKGROUP_SIZE", BATCH_WORKGROUP_SIZE);
    constant_u32(&mut s, "RENDER_TILE", RENDER_TILE);
    constant_u32(&mut s, "INFO_HIT", INFO_HIT);
    constant_u32(&mut s, "INFO_EXHAUSTED", INFO_EXHAUSTED);
    constant_u32(&mut s, "INFO_MALFORMED", INFO_MALFORMED);
    constant_u32(&mut s, "INFO_LEVEL_SHIFT", INFO_LEVEL_SHIFT);
    constant_u32(&mut s, "INFO_FACE_SHIFT", INFO_FACE_SHIFT);
    constant_u32(&mut s, "RAY_SKIP", RAY_SKIP);
    constant_u32(&mut s, "RAY_HOST_ANSWER", RAY_HOST_ANSWER);
    constant_u32(&mut s, "RAY_MOVING_SHIFT", RAY_MOVING_SHIFT);
    constant_u32(&mut s, "INFO_HOST_ANSWER", INFO_HOST_ANSWER);
    constant_u32(&mut s, "INFO_SKIPPED", INFO_SKIPPED);
    constant_f32(&mut s, "PARAMETER_BOUND", PARAMETER_BOUND);
    constant_u32(&mut s, "OPTION_INDEX", OPTION_INDEX);
    constant_u32(&mut s, "OPTION_WRITE_HITS", OPTION_WRITE_HITS);
    constant_u32(&mut s, "OPTION_WRITE_IMAGE", OPTION_WRITE_IMAGE);
    constant_u32(&mut s, "FACE_INSIDE", FACE_INSIDE);
    constant_u32(&mut s, "CHILD_MASK_BITS", CHILD_MASK_BITS);
    constant_u32(&mut s, "COUNT_SATURATED", COUNT_SATURATED);
    constant_u32(&mut s, "NO_REPLAY", NO_REPLAY);
    constant_f32(&mut s, "TINY_DIRECTION_INVERSE", TINY_DIRECTION_INVERSE);
    constant_f32(&mut s, "RENDER_FAR", RENDER_FAR);
    constant_u32(&mut s, "STACK_SIZE", config.stack_size);
    // A full stack is indexed by level directly; a short one is a ring.
    constant_u32(
        &mut s,
        "STACK_MASK",
        if config.short_stack {
            config.stack_size - 1
        } else {
            u32::MAX
        },
    );
    let _ = writeln!(s, "const SHORT_STACK: bool = {};", config.short_stack);
    let _ = writeln!(s, "const FORMAT_V2: bool = {};", config.format_v2);
    let _ = writeln!(s, "const V2_IN_PLACE: bool = {};", config.v2_in_place());
    constant_u32(&mut s, "PAGE_COUNT", config.pages);
    s.push('\n');
    for decl in [
        GpuRay::wgsl_declaration(),
        GpuHit::wgsl_declaration(),
        GpuParams::wgsl_declaration(),
    ] {
        s.push_str(&decl);
        s.push('\n');
    }
    let _ = writeln!(
        s,
        "@group({GROUP_IO}) @binding({BINDING_PARAMS}) var<uniform> params: GpuParams;"
    );
    let _ = writeln!(
        s,
        "@group({GROUP_IO}) @binding({BINDING_RAYS}) var<storage, read> rays: array<GpuRay>;"
    );
    let _ = writeln!(
        s,
        "@group({GROUP_IO}) @binding({BINDING_HITS}) var<storage, read_write> hits: array<GpuHit>;"
    );
    let _ = writeln!(
        s,
        "@group({GROUP_IO}) @binding({BINDING_IMAGE}) var<storage, read_write> image: array<u32>;"
    );
    for page in 0..config.pages {
        let _ = writeln!(
            s,
            "@group({GROUP_PAGES}) @binding({page}) var<storage, read> page{page}: array<u32>;"
        );
    }
    s.push('\n');
    s.push_str(
        "// Word `a` of the DAG's address space (levels, then the saturated-count table).\n",
    );
    push_paged_load(&mut s, "load_word", "page", config.pages, config.page_shift);
    s
}

/// Writes the WGSL function `name(a: u32) -> u32` that loads word `a` of an
/// address space split into `pages` bindings `{array}0`, `{array}1`, … of
/// `2^page_shift` words each (0 past the last page).
fn push_paged_load(s: &mut String, name: &str, array: &str, pages: u32, page_shift: u32) {
    let _ = writeln!(s, "fn {name}(a: u32) -> u32 {{");
    if pages == 1 {
        let _ = writeln!(s, "    return {array}0[a];");
    } else {
        let _ = writeln!(s, "    let offset = a & {}u;", (1u32 << page_shift) - 1);
        let _ = writeln!(s, "    switch (a >> {page_shift}u) {{");
        for page in 0..pages {
            let _ = writeln!(
                s,
                "        case {page}u: {{ return {array}{page}[offset]; }}"
            );
        }
        s.push_str("        default: { return 0u; }\n    }\n");
    }
    s.push_str("}\n\n");
}

/// How the colour pass is specialised: fixed per tracer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(crate) struct ColorConfig {
    /// Whether the section is PACKED_COLORS (else VOXEL_COLORS).
    pub packed: bool,
    /// Storage bindings holding the section's words.
    pub pages: u32,
    /// log2 of the words per page (when there is more than one page).
    pub page_shift: u32,
}

/// The generated WGSL that precedes `colors.wgsl`: constants, the params
/// struct, the bindings and the page-switching loader `color_word`.
pub(crate) fn color_preamble(config: &ColorConfig) -> String {
    let mut s = String::from(
        "// Generated by dagtrace::gpu::layout from the Rust definitions. Do not edit.\n\n",
    );
    constant_u32(&mut s, "COLOR_WORKGROUP_SIZE", COLOR_WORKGROUP_SIZE);
    constant_u32(&mut s, "COLOR_DISPATCH_ROW", COLOR_DISPATCH_ROW);
    let _ = writeln!(s, "const COLORS_PACKED: bool = {};", config.packed);
    s.push('\n');
    s.push_str(&GpuColorParams::wgsl_declaration());
    s.push('\n');
    let _ = writeln!(
        s,
        "@group({GROUP_COLORS}) @binding({BINDING_COLOR_PARAMS}) var<uniform> cparams: GpuColorParams;"
    );
    let _ = writeln!(
        s,
        "@group({GROUP_COLORS}) @binding({BINDING_COLOR_RECORDS}) var<storage, read> records: array<u32>;"
    );
    let _ = writeln!(
        s,
        "@group({GROUP_COLORS}) @binding({BINDING_COLOR_OUT}) var<storage, read_write> colors_out: array<u32>;"
    );
    for page in 0..config.pages {
        let _ = writeln!(
            s,
            "@group({GROUP_COLORS}) @binding({}) var<storage, read> cpage{page}: array<u32>;",
            BINDING_COLOR_PAGES + page
        );
    }
    s.push_str("\n// Word `a` of the colour section (its bytes as little-endian words).\n");
    push_paged_load(
        &mut s,
        "color_word",
        "cpage",
        config.pages,
        config.page_shift,
    );
    s
}

/// The complete colour-pass shader for `config`.
pub(crate) fn color_shader_source(config: &ColorConfig) -> String {
    let mut s = color_preamble(config);
    s.push_str(include_str!("colors.wgsl"));
    s
}

/// The complete shader source for `config`.
pub(crate) fn shader_source(config: &ShaderConfig) -> String {
    let mut s = preamble(config);
    s.push_str(include_str!("trace.wgsl"));
    s.push_str(include_str!("batch.wgsl"));
    s
}
