//! Shader checks that need no adapter: the generated WGSL parses and
//! validates, and the shared structs have the same layout on both sides.

use super::layout::{
    self, FieldLayout, GpuHit, GpuParams, GpuRay, GpuStruct, MAX_PAGES, ShaderConfig,
};
use wgpu::naga;

fn configs() -> Vec<ShaderConfig> {
    let mut out = Vec::new();
    // Each configuration in the three variants: 1.0, 2.0 expanded and 2.0
    // in place.
    for (format_v2, expanded) in [(false, false), (true, true), (true, false)] {
        out.push(ShaderConfig {
            stack_size: layout::MAX_STORED_LEVELS as u32,
            short_stack: false,
            pages: 1,
            page_shift: 0,
            format_v2,
            expanded,
        });
        for stack_size in [1, 2, 4, 16] {
            out.push(ShaderConfig {
                stack_size,
                short_stack: true,
                pages: 3,
                page_shift: 14,
                format_v2,
                expanded,
            });
        }
        out.push(ShaderConfig {
            stack_size: 4,
            short_stack: true,
            pages: MAX_PAGES,
            page_shift: 20,
            format_v2,
            expanded,
        });
    }
    out
}

fn parse_and_validate(config: &ShaderConfig) -> naga::Module {
    let source = layout::shader_source(config);
    let module = naga::front::wgsl::parse_str(&source)
        .unwrap_or_else(|e| panic!("{}", e.emit_to_string(&source)));
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::default(),
    )
    .validate(&module)
    .unwrap_or_else(|e| panic!("{config:?}: {}", e.emit_to_string(&source)));
    module
}

#[test]
fn generated_shaders_parse_and_validate() {
    for config in configs() {
        let module = parse_and_validate(&config);
        let entries: Vec<&str> = module
            .entry_points
            .iter()
            .map(|e| e.name.as_str())
            .collect();
        // (`trace_batch` comes from batch.wgsl, appended after trace.wgsl.)
        for entry in ["trace_batch", "render_primary"] {
            assert!(entries.contains(&entry), "{config:?}: {entries:?}");
        }
    }
}

/// Offsets and sizes of the members of WGSL struct `name`, from naga's layout.
fn wgsl_layout(module: &naga::Module, name: &str) -> (Vec<(String, u32, u32)>, u32) {
    let mut layouter = naga::proc::Layouter::default();
    layouter.update(module.to_ctx()).expect("layouts");
    let (_, ty) = module
        .types
        .iter()
        .find(|(_, t)| t.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("no struct {name}"));
    let naga::TypeInner::Struct { members, span } = &ty.inner else {
        panic!("{name} is not a struct")
    };
    let fields = members
        .iter()
        .map(|m| {
            (
                m.name.clone().unwrap_or_default(),
                m.offset,
                layouter[m.ty].size,
            )
        })
        .collect();
    (fields, *span)
}

fn check_struct<T: GpuStruct>(module: &naga::Module) {
    let (wgsl, span) = wgsl_layout(module, T::NAME);
    let rust: Vec<(String, u32, u32)> = T::fields()
        .into_iter()
        .map(
            |FieldLayout {
                 name, offset, size, ..
             }| (name.to_string(), offset as u32, size as u32),
        )
        .collect();
    assert_eq!(wgsl, rust, "member layout of {}", T::NAME);
    assert_eq!(span as usize, size_of::<T>(), "size of {}", T::NAME);
}

#[test]
fn shared_structs_have_the_same_layout_in_rust_and_wgsl() {
    let module = parse_and_validate(&configs()[0]);
    check_struct::<GpuRay>(&module);
    check_struct::<GpuHit>(&module);
    check_struct::<GpuParams>(&module);
}

#[test]
fn preamble_carries_the_rust_constants() {
    let source = layout::preamble(&configs()[1]);
    for line in [
        format!("const INFO_HIT: u32 = {}u;", layout::INFO_HIT),
        format!(
            "const COUNT_SATURATED: u32 = {}u;",
            dagfmt::layout::COUNT_SATURATED
        ),
        format!(
            "const MAX_STORED_LEVELS: u32 = {}u;",
            dagfmt::layout::MAX_DEPTH - 1
        ),
        "const STACK_SIZE: u32 = 1u;".to_string(),
        "const STACK_MASK: u32 = 0u;".to_string(),
        "const SHORT_STACK: bool = true;".to_string(),
        "const FORMAT_V2: bool = false;".to_string(),
        "const V2_IN_PLACE: bool = false;".to_string(),
        "case 2u: { return page2[offset]; }".to_string(),
    ] {
        assert!(source.contains(&line), "missing `{line}` in\n{source}");
    }
    let module =
        naga::front::wgsl::parse_str(&layout::shader_source(&configs()[0])).expect("parses");
    let tiny = module
        .constants
        .iter()
        .find(|(_, c)| c.name.as_deref() == Some("TINY_DIRECTION_INVERSE"))
        .map(|(_, c)| c.init)
        .expect("constant");
    match module.global_expressions[tiny] {
        naga::Expression::Literal(naga::Literal::F32(v)) => {
            assert_eq!(v, layout::TINY_DIRECTION_INVERSE)
        }
        ref e => panic!("unexpected {e:?}"),
    }
}

#[test]
fn lit_shader_parses_validates_and_shares_layouts() {
    use super::lit::{GpuLitParams, GpuSurface};
    for config in configs() {
        let source = super::lit::shader_source(&config);
        let module = naga::front::wgsl::parse_str(&source)
            .unwrap_or_else(|e| panic!("{}", e.emit_to_string(&source)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::default(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{config:?}: {}", e.emit_to_string(&source)));
        // The order of entry points follows the concatenated sources; only the set matters.
        let mut entries: Vec<&str> = module
            .entry_points
            .iter()
            .map(|e| e.name.as_str())
            .collect();
        entries.sort_unstable();
        assert_eq!(
            entries,
            [
                "lit_ao",
                "lit_primary",
                "lit_shadow",
                "render_primary",
                "trace_batch",
            ],
            "{config:?}"
        );
        check_struct::<GpuSurface>(&module);
        check_struct::<GpuLitParams>(&module);
    }
}

#[test]
fn colour_shader_parses_validates_and_shares_its_layout() {
    use super::layout::{ColorConfig, GpuColorParams};
    for (packed, pages, page_shift) in [(true, 1, 0), (false, 1, 0), (true, 5, 12), (false, 14, 20)]
    {
        let config = ColorConfig {
            packed,
            pages,
            page_shift,
        };
        let source = layout::color_shader_source(&config);
        let module = naga::front::wgsl::parse_str(&source)
            .unwrap_or_else(|e| panic!("{}", e.emit_to_string(&source)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::default(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{config:?}: {}", e.emit_to_string(&source)));
        let entries: Vec<&str> = module
            .entry_points
            .iter()
            .map(|e| e.name.as_str())
            .collect();
        assert_eq!(entries, ["record_colors"], "{config:?}");
        check_struct::<GpuColorParams>(&module);
        if pages > 1 {
            let line = format!(
                "case {}u: {{ return cpage{}[offset]; }}",
                pages - 1,
                pages - 1
            );
            assert!(source.contains(&line), "missing `{line}`");
        }
    }
}
