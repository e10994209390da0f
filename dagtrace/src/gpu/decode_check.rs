//! The WGSL decoder against the CPU's (`crate::node`): the decoding
//! functions of `trace.wgsl` (`record_address`, `node_mask`,
//! `node_attribute`, `child_reference`, `leaf_mask`), run on the device by a
//! test entry point over the nodes and leaves of real and random DAGs, give
//! what `node::Level` reads from the same bytes. The DAGs are also spread
//! over several storage bindings, so that `load_word`'s page choice is
//! checked too.
//!
//! The 2.0 decoder of `trace.wgsl` (`codes2`, `child2`, `record_size2`,
//! `reflect_leaf`; spec §23.2 – §23.4) is checked the same way against
//! `node::Level::new_v2` (which reads through `dagfmt::v2::Coding`) and
//! `node::logical_leaf`, over the records of random 2.0 DAGs and of the
//! conformance cases upgraded with `dagfmt::v2file::upgrade`.
//!
//! The expanded form of a 2.0 DAG (spec §23.12, `dagfmt::expand`: the
//! shader's default for 2.0) is checked the same way: `node_mask`,
//! `node_attribute` and `child_entry` of the expanded variant, run on the
//! device, give for every record the header, the child (its record's word
//! index in the expanded child level, or the leaf index) and the reflection
//! that `node::Level::new_v2` decodes from the file's bytes, the word
//! indices found by following the records' sizes (`Coding::record_size`).
//!
//! Without an adapter the test prints that it was skipped (a failure with
//! `VDAG_REQUIRE_GPU=1`), like the GPU tests in `dagtrace/tests/it/gpu.rs`.

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;

use dagfmt::builder::DagBuilder;
use dagfmt::layout::AttributeKind;
use dagfmt::v2::{Child, Coding, LevelView};
use dagfmt::v2file::upgrade;
use dagfmt::{Dag, Dag2};
use wgpu::util::DeviceExt;

use super::layout::{GpuHit, GpuRay, ShaderConfig};
use super::{AdapterChoice, GpuContext, GpuOptions, GpuTracer, V2Layout};
use crate::node::{Level, attribute, child_mask, logical_leaf};
use crate::testing::Rng;

/// The test entry point: query `i` (four words of `image`: kind, level,
/// pointer, child slot) is answered in the four words at `4 * (n + i)`.
const CHECK_WGSL: &str = r#"
@compute @workgroup_size(64)
fn check_decoding(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    let n = params.ray_count;
    if (i >= n) {
        return;
    }
    let kind = image[4u * i];
    let level = image[4u * i + 1u];
    let pointer = image[4u * i + 2u];
    let slot = image[4u * i + 3u];
    let a = record_address(level, pointer);
    let out = 4u * (n + i);
    if (kind == 0u) {
        let mask = node_mask(a);
        image[out] = mask;
        image[out + 1u] = node_attribute(a);
        image[out + 2u] = child_reference(a, level, mask, slot);
        image[out + 3u] = a;
    } else {
        let bits = leaf_mask(a);
        image[out] = bits.x;
        image[out + 1u] = bits.y;
        image[out + 2u] = 0u;
        image[out + 3u] = a;
    }
}
"#;

/// The 2.0 test entry point: query `i` (kind, level, byte offset or leaf
/// index, slot or leaf reflection) answered in the four words at `4 * (n +
/// i)`: node: header, child address, reflection | record size << 8, codes
/// count; leaf: the mask reflected by the query's reflection (low, high),
/// the stored mask's low word, 0.
const CHECK2_WGSL: &str = r#"
@compute @workgroup_size(64)
fn check_decoding(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    let n = params.ray_count;
    if (i >= n) {
        return;
    }
    let kind = image[4u * i];
    let level = image[4u * i + 1u];
    let at = image[4u * i + 2u];
    let slot = image[4u * i + 3u];
    let out = 4u * (n + i);
    if (kind == 0u) {
        let c = codes2(level, at);
        let child = child2(level, at, c, slot);
        image[out] = c.header;
        image[out + 1u] = child.x;
        image[out + 2u] = child.y | (record_size2(level, at) << 8u);
        image[out + 3u] = c.count;
    } else {
        let bits = leaf_mask(record_address(level, at));
        let r = reflect_leaf(bits, slot);
        image[out] = r.x;
        image[out + 1u] = r.y;
        image[out + 2u] = bits.x;
        image[out + 3u] = 0u;
    }
}
"#;

/// The expanded 2.0 test entry point: query `i` (kind, level, word index of
/// the record or leaf index, slot or leaf reflection) answered in the four
/// words at `4 * (n + i)`: node: header, child (word index or leaf index),
/// reflection, word address; leaf: as [`CHECK2_WGSL`].
const CHECK_EXPANDED_WGSL: &str = r#"
@compute @workgroup_size(64)
fn check_decoding(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    let n = params.ray_count;
    if (i >= n) {
        return;
    }
    let kind = image[4u * i];
    let level = image[4u * i + 1u];
    let pointer = image[4u * i + 2u];
    let slot = image[4u * i + 3u];
    let a = record_address(level, pointer);
    let out = 4u * (n + i);
    if (kind == 0u) {
        let mask = node_mask(a);
        let child = child_entry(a, level, mask, slot);
        image[out] = mask | (node_attribute(a) << CHILD_MASK_BITS);
        image[out + 1u] = child.x;
        image[out + 2u] = child.y;
        image[out + 3u] = a;
    } else {
        let bits = leaf_mask(a);
        let r = reflect_leaf(bits, slot);
        image[out] = r.x;
        image[out + 1u] = r.y;
        image[out + 2u] = bits.x;
        image[out + 3u] = 0u;
    }
}
"#;

/// Most queries of one DAG.
const MAX_QUERIES: usize = 6_000;

impl GpuTracer {
    /// The pipeline of [`CHECK_WGSL`] for this tracer's shader configuration.
    fn check_pipeline(&self) -> wgpu::ComputePipeline {
        let inner = &self.context.inner;
        let device = &inner.device;
        let mut source = super::layout::shader_source(&self.config);
        source.push_str(if self.config.v2_in_place() {
            CHECK2_WGSL
        } else if self.config.format_v2 {
            CHECK_EXPANDED_WGSL
        } else {
            CHECK_WGSL
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("vdag decode check"),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("vdag decode check"),
            bind_group_layouts: &[Some(&inner.io_layout), Some(&self.pipelines.pages_layout)],
            immediate_size: 0,
        });
        device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("check_decoding"),
            layout: Some(&layout),
            module: &module,
            entry_point: Some("check_decoding"),
            compilation_options: Default::default(),
            cache: None,
        })
    }

    /// Runs [`CHECK_WGSL`] on `queries` (kind, level, pointer, slot) and
    /// returns the four answer words of each; `pipelines` keeps the compiled
    /// check per shader configuration.
    fn decode_on_device(
        &self,
        queries: &[[u32; 4]],
        pipelines: &mut HashMap<ShaderConfig, wgpu::ComputePipeline>,
    ) -> Vec<[u32; 4]> {
        let inner = &self.context.inner;
        let device = &inner.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let pipeline = pipelines
            .entry(self.config)
            .or_insert_with(|| self.check_pipeline());
        let n = queries.len();
        let mut params = self.base_params;
        params.ray_count = n as u32;
        let params = self.params_buffer(&params);
        let mut words: Vec<u32> = queries.iter().flatten().copied().collect();
        words.resize(8 * n, 0);
        let image = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("vdag decode queries"),
            contents: bytemuck::cast_slice(&words),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        });
        let unused = |size: usize| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("vdag unused"),
                size: size as u64,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            })
        };
        let rays = unused(size_of::<GpuRay>());
        let hits = unused(size_of::<GpuHit>());
        let io = self.io_group(&params, &rays, &hits, &image);
        let mut encoder =
            device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &io, &[]);
            pass.set_bind_group(1, &self.pages_group, &[]);
            pass.dispatch_workgroups(n.div_ceil(64) as u32, 1, 1);
        }
        inner.queue.submit([encoder.finish()]);
        if let Some(e) = pollster::block_on(scope.pop()) {
            panic!("decode check shader: {e}");
        }
        let out: Vec<u32> = self
            .context
            .read_back(&image, (words.len() * 4) as u64)
            .expect("read back");
        out[4 * n..]
            .chunks_exact(4)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect()
    }
}

/// The shared context, or `None` (after saying so) when there is no adapter.
fn context() -> Option<GpuContext> {
    match GpuContext::new(AdapterChoice::Default) {
        Ok(c) => Some(c),
        Err(e) => {
            if std::env::var("VDAG_REQUIRE_GPU").is_ok_and(|v| v == "1") {
                panic!("VDAG_REQUIRE_GPU=1 but no GPU adapter: {e}");
            }
            println!("skipped: no GPU adapter (set VDAG_REQUIRE_GPU=1 to make this an error): {e}");
            None
        }
    }
}

/// Queries for up to [`MAX_QUERIES`] random records of `dag`: nodes (one
/// query per child, so every rank is asked for) and leaves, reached from the
/// root; and what the CPU's decoding answers for each (the fourth word, the
/// record's word address, is not compared).
fn queries(dag: &Dag<'_>, rng: &mut Rng) -> Vec<([u32; 4], [u32; 3])> {
    let levels: Vec<Level> = dag
        .levels()
        .iter()
        .map(|s| Level::new(dag.bytes(), s))
        .collect();
    let leaf_level = dag.leaf_level();
    let mut records = Vec::new();
    let mut seen = HashSet::new();
    let mut pending = if dag.is_empty() {
        vec![]
    } else {
        vec![(0u8, 0u32)]
    };
    while let Some((l, pointer)) = pending.pop() {
        if !seen.insert((l, pointer)) {
            continue;
        }
        records.push((l, pointer));
        if l == leaf_level {
            continue;
        }
        let level = &levels[usize::from(l)];
        let mask = child_mask(level.header(l, pointer).expect("a valid file"));
        for c in 0..8 {
            if mask >> c & 1 == 1 {
                let child = level.child(l, pointer, mask, c).expect("a valid file");
                pending.push((l + 1, child.node));
            }
        }
    }
    // A random sample, in random order.
    for i in (1..records.len()).rev() {
        records.swap(i, (rng.next() % (i as u64 + 1)) as usize);
    }
    let mut out = Vec::new();
    for (l, pointer) in records {
        let level = &levels[usize::from(l)];
        if l == leaf_level {
            let bits = level.leaf(l, pointer).expect("a valid file");
            out.push((
                [1, u32::from(l), pointer, 0],
                [bits as u32, (bits >> 32) as u32, 0],
            ));
        } else {
            let header = level.header(l, pointer).expect("a valid file");
            let mask = child_mask(header);
            for c in (0..8).filter(|c| mask >> c & 1 == 1) {
                let child = level.child(l, pointer, mask, c).expect("a valid file");
                out.push((
                    [0, u32::from(l), pointer, c],
                    [u32::from(mask), attribute(header), child.node],
                ));
            }
        }
        if out.len() >= MAX_QUERIES {
            break;
        }
    }
    out
}

/// The compiled checks, per shader configuration.
type Pipelines = HashMap<ShaderConfig, wgpu::ComputePipeline>;

/// Checks the device's decoding of `bytes` against the CPU's, with the DAG
/// on one storage binding and, where `pages`, spread over several.
fn check(
    ctx: &GpuContext,
    pipelines: &mut Pipelines,
    (name, bytes): (&str, &[u8]),
    pages: bool,
    rng: &mut Rng,
) -> usize {
    let dag = Dag::open(bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
    let asked = queries(&dag, rng);
    if asked.is_empty() {
        return 0;
    }
    let dag_bytes: usize = dag.levels().iter().map(|l| l.bytes.len()).sum();
    let small_pages = (dag_bytes as u64 / 3).next_power_of_two().max(64);
    let mut bindings = vec![None];
    if pages {
        bindings.push(Some(small_pages));
    }
    for max_binding_bytes in bindings {
        let options = GpuOptions {
            max_binding_bytes,
            ..GpuOptions::default()
        };
        let gpu = match GpuTracer::with_context(ctx, &dag, &options) {
            Ok(gpu) => gpu,
            // More pages than the device binds: the single binding is checked.
            Err(super::GpuError::TooLarge(_)) if max_binding_bytes.is_some() => continue,
            Err(e) => panic!("{name}: {e}"),
        };
        let query: Vec<[u32; 4]> = asked.iter().map(|(q, _)| *q).collect();
        let answers = gpu.decode_on_device(&query, pipelines);
        for ((q, expected), got) in asked.iter().zip(&answers) {
            assert_eq!(
                &got[..3],
                expected,
                "{name} ({} bindings): {} {} of level {} (slot {})",
                gpu.binding_count(),
                if q[0] == 0 { "node" } else { "leaf" },
                q[2],
                q[1],
                q[3]
            );
        }
    }
    asked.len()
}

/// The trace cases of the conformance suite (real files, as the suite ships
/// them) and random DAGs of several depths and densities, whose levels have
/// pointers of one to three bytes, the random ones also over several
/// storage bindings.
#[test]
fn wgsl_decoding_reads_nodes_and_leaves_as_the_cpu_does() {
    let Some(ctx) = context() else { return };
    let mut pipelines = Pipelines::new();
    let mut rng = Rng(0x36d);
    let mut checked = 0;
    for file in &conformance_case_files() {
        let bytes = std::fs::read(file).expect("a case file");
        let name = file.display().to_string();
        checked += check(&ctx, &mut pipelines, (&name, &bytes), false, &mut rng);
    }
    let mut widths = HashSet::new();
    for (depth, voxels, clusters) in RANDOM_DAGS {
        let bytes = random_dag(depth, voxels, clusters, &mut rng);
        let dag = Dag::open(&bytes).expect("built DAG opens");
        widths.extend(
            dag.levels()
                .iter()
                .filter(|l| !l.is_leaf)
                .map(|l| l.pointer_width),
        );
        let name = format!("random depth {depth}");
        checked += check(&ctx, &mut pipelines, (&name, &bytes), true, &mut rng);
    }
    println!("{checked} records decoded alike; pointer widths {widths:?}");
    assert!(widths.len() >= 2, "pointer widths {widths:?}");
}

/// Queries of up to [`MAX_QUERIES`] random records of the 2.0 `levels`:
/// nodes (one query per child) and leaves (with a random reflection),
/// reached from the root; and what the CPU's decoding (`node::Level`,
/// `dagfmt::v2::Coding`, `node::logical_leaf`) answers for each: node:
/// header, child address, reflection | size << 8; leaf: the reflected mask
/// and the stored mask's low word.
fn queries_v2(
    levels: &[LevelView<'_>],
    rng: &mut Rng,
    seen_kinds: &mut [usize; 4],
) -> Vec<([u32; 4], [u32; 3])> {
    let decoders: Vec<Level> = (0..levels.len())
        .map(|l| Level::new_v2(&levels[l], levels.get(l + 1), None).expect("valid levels"))
        .collect();
    let leaf_level = (levels.len() - 1) as u8;
    let mut records = Vec::new();
    let mut seen = HashSet::new();
    let mut pending = if levels[0].item_count == 0 {
        vec![]
    } else {
        vec![(0u8, 0u32)]
    };
    while let Some((l, at)) = pending.pop() {
        if !seen.insert((l, at)) {
            continue;
        }
        records.push((l, at));
        if l == leaf_level {
            continue;
        }
        let level = &decoders[usize::from(l)];
        let mask = child_mask(level.header(l, at).expect("a valid file"));
        for c in (0..8).filter(|c| mask >> c & 1 == 1) {
            let child = level.child(l, at, mask, c).expect("a valid file");
            pending.push((l + 1, child.node));
        }
    }
    for i in (1..records.len()).rev() {
        records.swap(i, (rng.next() % (i as u64 + 1)) as usize);
    }
    let mut out = Vec::new();
    for (l, at) in records {
        let level = &decoders[usize::from(l)];
        if l == leaf_level {
            let bits = level.leaf(l, at).expect("a valid file");
            let r = (rng.next() % 8) as u8;
            let logical = logical_leaf(bits, r);
            out.push((
                [1, u32::from(l), at, u32::from(r)],
                [logical as u32, (logical >> 32) as u32, bits as u32],
            ));
        } else {
            let view = &levels[usize::from(l)];
            let coding = Coding::new(view.widths).expect("valid widths");
            let size = coding
                .record_size(view.bytes, u64::from(at))
                .expect("a record") as u32;
            let header = level.header(l, at).expect("a valid file");
            let mask = child_mask(header);
            let codes = coding.codes(view.bytes, u64::from(at)).expect("codes");
            for c in (0..8).filter(|c| mask >> c & 1 == 1) {
                let child = level.child(l, at, mask, c).expect("a valid file");
                match coding.child(view.bytes, u64::from(at), &codes, c) {
                    Some(Child::Shared { reflection, .. }) => {
                        seen_kinds[usize::from(reflection != 0)] += 1
                    }
                    Some(Child::Sequential { index, .. }) => {
                        seen_kinds[2 + usize::from(index > 0 && l + 1 < leaf_level)] += 1
                    }
                    None => panic!("a valid record"),
                }
                out.push((
                    [0, u32::from(l), at, c],
                    [header, child.node, u32::from(child.reflection) | size << 8],
                ));
            }
        }
        if out.len() >= MAX_QUERIES {
            break;
        }
    }
    out
}

/// The word index each record of each node level of `levels` has in the
/// expanded level (spec §23.12: a header word, then a word per child, in
/// the file's record order), found by following the records' sizes.
fn expanded_word_indices(levels: &[LevelView<'_>]) -> Vec<HashMap<u32, u32>> {
    levels
        .iter()
        .filter(|l| !l.is_leaf)
        .map(|view| {
            let mut words = HashMap::new();
            if view.bytes.is_empty() {
                return words;
            }
            let coding = Coding::new(view.widths).expect("valid widths");
            let (mut at, mut word) = (0u64, 0u32);
            while at < view.bytes.len() as u64 {
                let codes = coding.codes(view.bytes, at).expect("a record");
                words.insert(at as u32, word);
                word += 1 + codes.child_mask().count_ones();
                at += coding.record_size(view.bytes, at).expect("a record");
            }
            words
        })
        .collect()
}

/// [`queries_v2`] for the expanded form: record queries name the record's
/// word index, and their answers the child's word index (a leaf's index on
/// the leaf level) and the reflection.
fn expanded_queries(
    levels: &[LevelView<'_>],
    asked: Vec<([u32; 4], [u32; 3])>,
) -> Vec<([u32; 4], [u32; 3])> {
    let words = expanded_word_indices(levels);
    let leaf_level = (levels.len() - 1) as u32;
    asked
        .into_iter()
        .map(|(q, expected)| {
            if q[0] != 0 {
                return (q, expected);
            }
            let l = q[1] as usize;
            let child = if q[1] + 1 < leaf_level {
                words[l + 1][&expected[1]]
            } else {
                expected[1]
            };
            (
                [q[0], q[1], words[l][&q[2]], q[3]],
                [expected[0], child, expected[2] & 0xff],
            )
        })
        .collect()
}

/// Checks the device's 2.0 decoding of the 2.0 file `bytes` against the
/// CPU's, in the layout `layout`, on one storage binding and, where
/// `pages`, on several.
fn check_v2(
    ctx: &GpuContext,
    pipelines: &mut Pipelines,
    (name, bytes): (&str, &[u8]),
    (pages, layout): (bool, V2Layout),
    rng: &mut Rng,
    seen_kinds: &mut [usize; 4],
) -> usize {
    let dag = Dag2::open(bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
    let mut asked = queries_v2(dag.levels(), rng, seen_kinds);
    if layout == V2Layout::Expanded {
        asked = expanded_queries(dag.levels(), asked);
    }
    if asked.is_empty() {
        return 0;
    }
    let dag_bytes: usize = dag.levels().iter().map(|l| l.bytes.len()).sum();
    let small_pages = (dag_bytes as u64 / 3).next_power_of_two().max(64);
    let mut bindings = vec![None];
    if pages {
        bindings.push(Some(small_pages));
    }
    for max_binding_bytes in bindings {
        let options = GpuOptions {
            max_binding_bytes,
            v2_layout: layout,
            ..GpuOptions::default()
        };
        let gpu = match GpuTracer::with_context_v2(ctx, dag.header(), dag.levels(), None, &options)
        {
            Ok(gpu) => gpu,
            Err(super::GpuError::TooLarge(_)) if max_binding_bytes.is_some() => continue,
            Err(e) => panic!("{name}: {e}"),
        };
        assert_eq!(gpu.v2_layout(), Some(layout), "{name}");
        let query: Vec<[u32; 4]> = asked.iter().map(|(q, _)| *q).collect();
        let answers = gpu.decode_on_device(&query, pipelines);
        for ((q, expected), got) in asked.iter().zip(&answers) {
            assert_eq!(
                &got[..3],
                expected,
                "{name} ({layout:?}, {} bindings): {} {} of level {} (slot or reflection {})",
                gpu.binding_count(),
                if q[0] == 0 { "record" } else { "leaf" },
                q[2],
                q[1],
                q[3]
            );
        }
    }
    asked.len()
}

/// The 2.0 decoder: the conformance trace cases upgraded to 2.0, and random
/// 2.0 DAGs of several depths (also over several storage bindings), whose
/// references include reflected shared children and sequential children
/// after the first in interior levels (found by summing record sizes).
#[test]
fn wgsl_decoding_reads_2_0_records_and_leaves_as_the_cpu_does() {
    check_2_0_decoding(V2Layout::InPlace);
}

/// The expanded 2.0 decoder (spec §23.12), on the same DAGs: each child
/// word read on the device is the child and reflection the CPU decodes
/// from the file's record.
#[test]
fn wgsl_decoding_reads_expanded_2_0_levels_as_the_cpu_does() {
    check_2_0_decoding(V2Layout::Expanded);
}

fn check_2_0_decoding(layout: V2Layout) {
    let Some(ctx) = context() else { return };
    let mut pipelines = Pipelines::new();
    let mut rng = Rng(0x42);
    let mut checked = 0;
    // Shared unreflected, shared reflected, sequential first (or leaf),
    // sequential later in an interior level.
    let mut kinds = [0usize; 4];
    for file in &conformance_case_files() {
        let bytes = std::fs::read(file).expect("a case file");
        let upgraded = upgrade(&Dag::open(&bytes).expect("a case opens")).expect("upgrade");
        let name = format!("{} (2.0)", file.display());
        checked += check_v2(
            &ctx,
            &mut pipelines,
            (&name, &upgraded),
            (false, layout),
            &mut rng,
            &mut kinds,
        );
    }
    let mut widths = HashSet::new();
    for (depth, voxels, clusters) in RANDOM_DAGS {
        let bytes = random_dag(depth, voxels, clusters, &mut rng);
        let upgraded = upgrade(&Dag::open(&bytes).expect("built DAG opens")).expect("upgrade");
        let dag = Dag2::open(&upgraded).expect("upgraded DAG opens");
        widths.extend(dag.levels().iter().filter(|l| !l.is_leaf).map(|l| l.widths));
        let name = format!("random depth {depth} (2.0)");
        checked += check_v2(
            &ctx,
            &mut pipelines,
            (&name, &upgraded),
            (true, layout),
            &mut rng,
            &mut kinds,
        );
    }
    println!("{layout:?}: {checked} 2.0 records decoded alike; kinds {kinds:?}; widths {widths:?}");
    assert!(kinds.iter().all(|&n| n > 0), "kinds of children {kinds:?}");
    assert!(widths.len() >= 3, "widths {widths:?}");
}

/// The random DAGs both checks decode: (depth, voxels, clusters), uniform
/// when `clusters` is 0.
const RANDOM_DAGS: [(u8, usize, usize); 4] = [
    (5, 60, 2),
    (8, 4_000, 6),
    (10, 60_000, 20),
    (12, 150_000, 0),
];

/// A 1.0 file of `voxels` random voxels at `depth`, uniform or around
/// `clusters` random centres (so that some subtrees repeat and some do not).
fn random_dag(depth: u8, voxels: usize, clusters: usize, rng: &mut Rng) -> Vec<u8> {
    let side = 1u64 << depth;
    let points: Vec<[u32; 3]> = if clusters == 0 {
        (0..voxels)
            .map(|_| [0; 3].map(|_| (rng.next() % side) as u32))
            .collect()
    } else {
        let centres: Vec<[u64; 3]> = (0..clusters)
            .map(|_| [0; 3].map(|_| rng.next() % side))
            .collect();
        (0..voxels)
            .map(|i| {
                let c = centres[i % clusters];
                let spread = side / 8 + 1;
                c.map(|v| ((v + rng.next() % spread).min(side - 1)) as u32)
            })
            .collect()
    };
    DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, points)
        .expect("valid voxels")
        .to_bytes()
}

/// The `.vdag` files of the conformance suite's trace cases, sorted.
fn conformance_case_files() -> Vec<PathBuf> {
    let cases = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../conformance/cases/trace");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&cases)
        .expect("the conformance cases")
        .map(|e| e.expect("a directory entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "vdag"))
        .collect();
    files.sort();
    assert!(!files.is_empty(), "no .vdag in {}", cases.display());
    files
}
