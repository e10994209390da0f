//! The GPU tracer: the CPU tracer's traversal as a WGSL compute shader (wgpu).
//!
//! [`GpuTracer::new`] uploads the DAG's level sections straight from the
//! (memory-mapped) file bytes into GPU storage buffers, in bounded chunks;
//! [`GpuTracer::trace`] traces a batch of [`dagfmt::batch::Ray`]s with the
//! semantics of spec/VDAG.md (the same cells as [`crate::Tracer`] but at
//! exact ties, where both are within the tolerance of the semantics);
//! [`GpuTracer::render`] makes and traces camera rays on the GPU.
//! [`GpuTracer::with_context_v2`] uploads a format 2.0 DAG (spec §23) and
//! traces it with the 2.0 variant of the shader, with the answers of the 1.0
//! DAG of the same voxels (the lit passes too): by default its node levels
//! expanded into aligned words (`dagfmt::expand`, spec §23.12), so that a
//! child is one load as in 1.0; [`V2Layout`] says how.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use dagtrace::gpu::{GpuOptions, GpuTracer};
//! let file = dagfmt::mmap::MappedFile::open("model.vdag".as_ref())?;
//! let dag = dagfmt::Dag::open(file.bytes())?;
//! let gpu = GpuTracer::new(&dag, &GpuOptions::default())?;
//! let ray = dagfmt::batch::Ray::new([0.0, 0.5, 0.5], [1.0, 0.0, 0.0]);
//! let hits = gpu.trace(&[ray])?;
//! # Ok(()) }
//! ```
//!
//! # How the work is split
//!
//! - Host (f64, `prepare.rs`): the CPU tracer's set-up of each ray (world to
//!   grid space, scaling, mirroring; rays that need no DAG answered there),
//!   written straight into the GPU's upload buffer on all cores.
//! - Shader (f32, `trace.wgsl`, `batch.wgsl`): the traversal, finding the
//!   cell, its entry parameter and face (as the CPU tracer computes them),
//!   and the dense attribute index of the hit (with a host-made table of the
//!   counts of saturated nodes).
//! - Batches stream through the GPU in chunks, the host setting one up while
//!   the GPU traces the one before (`batch.rs`); memory is bounded by two
//!   chunks whatever the batch size.
//!
//! The shader and the host share their records and constants through
//! `layout.rs`, which generates the WGSL declarations.
//!
//! # Large DAGs and malformed files
//!
//! A DAG larger than one storage binding is spread over several bindings
//! ("pages"); [`GpuOptions::max_binding_bytes`] forces small pages (to test
//! this). Every shader read is bounds-checked by wgpu, a pointer leading
//! outside its level stops the ray ([`GpuError::MalformedPointer`]), and a ray
//! gives up after [`GpuOptions::max_iterations`] loop iterations
//! ([`GpuError::IterationLimit`]), so no file can hang the GPU. Other damage a
//! validator would catch gives wrong answers, not failures.

mod batch;
mod colors;
mod layout;
mod lit;
mod prepare;
#[cfg(target_arch = "x86_64")]
mod setup4;
mod upload;

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use dagfmt::batch::{Hit, Ray};
use dagfmt::layout::AttributeKind;
use dagfmt::{Dag, FormatError};
use glam::DVec3;
use wgpu::util::DeviceExt as _;

use crate::camera::{Camera, CameraError};
use dagfmt::v2::LevelView;
use layout::{
    BATCH_WORKGROUP_SIZE, BINDING_HITS, BINDING_IMAGE, BINDING_PARAMS, BINDING_RAYS, GpuHit,
    GpuParams, INFO_EXHAUSTED, INFO_FACE_SHIFT, INFO_HIT, INFO_LEVEL_SHIFT, INFO_MALFORMED,
    IO_STORAGE_BUFFERS, MAX_PAGES, MAX_STORED_LEVELS, OPTION_INDEX, OPTION_WRITE_HITS,
    OPTION_WRITE_IMAGE, RENDER_TILE, ShaderConfig,
};
pub use lit::LitTimes;
use prepare::Frame;
use upload::{Placement, UploadLevel};

/// Why the GPU tracer cannot do what was asked.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum GpuError {
    /// No wgpu adapter, not even a software one (for example, no Vulkan driver).
    #[error("no GPU adapter (not even a software one such as Mesa's lavapipe)")]
    NoAdapter,
    /// The device could not be created, was lost, or a GPU operation failed.
    #[error("GPU device error: {0}")]
    Device(String),
    /// The shader failed to compile (a bug, or an adapter lacking a WGSL feature).
    #[error("GPU shader error: {0}")]
    Shader(String),
    /// The DAG does not fit the device.
    #[error("the DAG is too large for the GPU: {0}")]
    TooLarge(String),
    /// The DAG is malformed where the host had to read it.
    #[error("malformed DAG: {0}")]
    Malformed(FormatError),
    /// The shader met a child pointer leading outside its level.
    #[error("malformed DAG: ray {ray} met a child pointer outside its level")]
    MalformedPointer {
        /// Index of the ray in the batch (or of the pixel).
        ray: usize,
    },
    /// A ray needed more loop iterations than allowed.
    #[error("ray {ray} exceeded the GPU iteration limit of {limit}")]
    IterationLimit {
        /// Index of the ray in the batch (or of the pixel).
        ray: usize,
        /// The limit.
        limit: u32,
    },
    /// A ray asks for a level of detail deeper than the DAG.
    #[error("ray {ray} asks for level {level}, deeper than the DAG's depth {depth}")]
    LevelTooDeep {
        /// Index of the ray in the batch.
        ray: usize,
        /// The level asked for.
        level: u8,
        /// The DAG's depth.
        depth: u8,
    },
    /// Options that cannot work.
    #[error("invalid GPU tracer options: {0}")]
    InvalidOptions(String),
    /// The camera cannot make rays.
    #[error("{0}")]
    Camera(#[from] CameraError),
}

/// Which adapter to use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum AdapterChoice {
    /// The default (high-performance) adapter, falling back to a software one.
    #[default]
    Default,
    /// Only a software adapter (such as lavapipe).
    Software,
}

/// The traversal stack of the shader.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum StackMode {
    /// One entry per level: no restarts.
    #[default]
    Full,
    /// A ring of this many entries (a power of two, 1 to 16). When the
    /// traversal returns to a level whose entry was overwritten, it restarts
    /// from the root along the current path, recomputing the entries exactly;
    /// answers are identical to [`StackMode::Full`]'s.
    Short(u32),
}

/// How the node levels of a format 2.0 DAG are laid out on the device.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum V2Layout {
    /// Expanded once at upload (`dagfmt::expand::expand_levels`, spec
    /// §23.12): 1.0-like records of aligned 32-bit words, a child one word
    /// `index << 3 | r`, read with one load. A DAG whose levels do not
    /// expand (a malformed one) is traced [`V2Layout::InPlace`], where each
    /// fault is reported as before ([`GpuTracer::v2_layout`] says which).
    /// Costs 4 bytes per node and per child on the device instead of the
    /// file's level bytes.
    #[default]
    Expanded,
    /// The file's record bytes as they are (spec §23.2), decoded by the
    /// shader, with a record-start bit vector per level (spec §23.8).
    InPlace,
}

/// How a [`GpuTracer`] is set up.
#[derive(Clone, Debug, PartialEq)]
pub struct GpuOptions {
    /// Adapter preference (used when the tracer makes its own context).
    pub adapter: AdapterChoice,
    /// The traversal stack.
    pub stack: StackMode,
    /// Largest storage binding to use, in bytes (the device's limit when
    /// `None`). Lower it to force the DAG over several bindings.
    pub max_binding_bytes: Option<u64>,
    /// Loop iterations after which a ray gives up. `None`: a bound no ray of
    /// a valid DAG reaches (it visits at most a few nodes per cell it crosses
    /// on each level).
    pub max_iterations: Option<u32>,
    /// Rays per dispatch: the chunk a batch is streamed in. Two chunks are
    /// in flight at once (one traced while the next is set up), and their
    /// buffers, 160 bytes a ray each, are kept between calls.
    pub rays_per_dispatch: u32,
    /// Whether hits carry the dense attribute index (attribute kind 1).
    pub compute_index: bool,
    /// Whether to upload the file's colour section (VOXEL_COLORS or
    /// PACKED_COLORS, as stored: a packed one stays compressed on the
    /// device), so that colours are looked up on the device
    /// ([`GpuTracer::hit_colors`], [`GpuTracer::render_lit_colored`]).
    /// Ignored for a file without colours or without attribute kind 1.
    pub colors: bool,
    /// How a format 2.0 DAG's node levels go to the device (ignored for
    /// 1.0).
    pub v2_layout: V2Layout,
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions {
            adapter: AdapterChoice::Default,
            stack: StackMode::Full,
            max_binding_bytes: None,
            max_iterations: None,
            rays_per_dispatch: 1 << 18,
            compute_index: true,
            colors: false,
            v2_layout: V2Layout::Expanded,
        }
    }
}

/// A device and queue, with the compiled shaders cached. Cheap to clone;
/// several tracers can share one.
#[derive(Clone, Debug)]
pub struct GpuContext {
    inner: Arc<ContextInner>,
}

#[derive(Debug)]
struct ContextInner {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    limits: wgpu::Limits,
    io_layout: wgpu::BindGroupLayout,
    /// Placeholder for the bindings an entry point does not use.
    dummy: wgpu::Buffer,
    pipelines: Mutex<HashMap<ShaderConfig, Arc<Pipelines>>>,
    /// The colour passes compiled so far (`colors.rs`).
    color_pipelines: Mutex<HashMap<layout::ColorConfig, Arc<colors::ColorPipeline>>>,
}

#[derive(Debug)]
struct Pipelines {
    pages_layout: wgpu::BindGroupLayout,
    batch: wgpu::ComputePipeline,
    render: wgpu::ComputePipeline,
}

fn device_error(e: impl std::fmt::Display) -> GpuError {
    GpuError::Device(e.to_string())
}

impl GpuContext {
    /// Opens an adapter (see [`AdapterChoice`]) and creates a device.
    pub fn new(choice: AdapterChoice) -> Result<Self, GpuError> {
        // The primary backends (Vulkan, Metal, DX12) have the compute features the
        // shader needs; `WGPU_BACKEND` overrides the choice.
        let descriptor = wgpu::InstanceDescriptor {
            backends: wgpu::Backends::PRIMARY,
            ..wgpu::InstanceDescriptor::new_without_display_handle()
        };
        let instance = wgpu::Instance::new(descriptor.with_env());
        let request = |force_fallback_adapter| {
            pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                force_fallback_adapter,
                compatible_surface: None,
                apply_limit_buckets: false,
            }))
        };
        let adapter = match choice {
            AdapterChoice::Default => request(false).or_else(|_| request(true)),
            AdapterChoice::Software => request(true),
        }
        .map_err(|_| GpuError::NoAdapter)?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("vdag"),
            required_limits: limits.clone(),
            memory_hints: wgpu::MemoryHints::Performance,
            ..Default::default()
        }))
        .map_err(device_error)?;
        let io_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("vdag io"),
            entries: &[
                uniform::<GpuParams>(BINDING_PARAMS),
                storage(BINDING_RAYS, true),
                storage(BINDING_HITS, false),
                storage(BINDING_IMAGE, false),
            ],
        });
        let dummy = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("vdag placeholder"),
            size: 256,
            usage: wgpu::BufferUsages::STORAGE,
            mapped_at_creation: false,
        });
        Ok(GpuContext {
            inner: Arc::new(ContextInner {
                device,
                queue,
                info,
                limits,
                io_layout,
                dummy,
                pipelines: Mutex::new(HashMap::new()),
                color_pipelines: Mutex::new(HashMap::new()),
            }),
        })
    }

    /// The adapter in use.
    pub fn adapter_info(&self) -> &wgpu::AdapterInfo {
        &self.inner.info
    }

    /// A one-line description of the adapter: name, type and backend.
    pub fn adapter_name(&self) -> String {
        let i = &self.inner.info;
        format!("{} ({:?}, {:?})", i.name, i.device_type, i.backend)
    }

    /// Whether the adapter is a software one (runs on the CPU).
    pub fn is_software(&self) -> bool {
        self.inner.info.device_type == wgpu::DeviceType::Cpu
    }

    /// The storage bindings available for the DAG's pages.
    fn max_pages(&self) -> u32 {
        self.inner
            .limits
            .max_storage_buffers_per_shader_stage
            .saturating_sub(IO_STORAGE_BUFFERS)
            .min(MAX_PAGES)
    }

    /// The largest storage binding the device allows, in bytes.
    pub fn max_binding_bytes(&self) -> u64 {
        self.inner
            .limits
            .max_storage_buffer_binding_size
            .min(self.inner.limits.max_buffer_size)
    }

    /// The compiled pipelines for `config` (compiled once per context).
    fn pipelines(&self, config: ShaderConfig) -> Result<Arc<Pipelines>, GpuError> {
        let mut cache = self
            .inner
            .pipelines
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if let Some(p) = cache.get(&config) {
            return Ok(p.clone());
        }
        let device = &self.inner.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("vdag trace.wgsl"),
            source: wgpu::ShaderSource::Wgsl(layout::shader_source(&config).into()),
        });
        let entries: Vec<wgpu::BindGroupLayoutEntry> = (0..config.pages)
            .map(|binding| wgpu::BindGroupLayoutEntry {
                binding,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only: true },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            })
            .collect();
        let pages_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("vdag pages"),
            entries: &entries,
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("vdag"),
            bind_group_layouts: &[Some(&self.inner.io_layout), Some(&pages_layout)],
            immediate_size: 0,
        });
        let pipeline = |entry| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let batch = pipeline("trace_batch");
        let render = pipeline("render_primary");
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Shader(e.to_string()));
        }
        let p = Arc::new(Pipelines {
            pages_layout,
            batch,
            render,
        });
        cache.insert(config, p.clone());
        Ok(p)
    }

    /// Waits for the queue to drain.
    fn wait(&self) -> Result<(), GpuError> {
        self.inner
            .device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(device_error)?;
        Ok(())
    }

    /// Reads `size` bytes of `buffer` (which must have `COPY_SRC`) back to the host.
    fn read_back<T: bytemuck::Pod>(
        &self,
        buffer: &wgpu::Buffer,
        size: u64,
    ) -> Result<Vec<T>, GpuError> {
        let device = &self.inner.device;
        let staging = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("vdag read-back"),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut encoder =
            device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        encoder.copy_buffer_to_buffer(buffer, 0, &staging, 0, size);
        self.inner.queue.submit([encoder.finish()]);
        let (sender, receiver) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = sender.send(r);
        });
        self.wait()?;
        receiver
            .recv()
            .map_err(device_error)?
            .map_err(device_error)?;
        // One copy, from the mapped bytes straight into the typed vector.
        let values =
            bytemuck::pod_collect_to_vec(&staging.get_mapped_range(..).map_err(device_error)?);
        staging.unmap();
        Ok(values)
    }
}

/// Counters of one traced batch.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TraceStats {
    /// Rays traced by the shader (the others were answered on the host and
    /// handed to it flagged to be skipped).
    pub gpu_rays: u64,
    /// Time from the first chunk's submission to the completion of the
    /// last one's, as the host saw it: the dispatches with the copies of
    /// rays in and hits out (the host's work on other chunks overlaps it).
    pub gpu_time: Duration,
    /// Time the host spent on its own share: the rays' set-up and the
    /// answers (on all cores), not waiting for the GPU.
    pub host_time: Duration,
    /// Time of the whole call.
    pub total_time: Duration,
    /// Sum of the traversal loop iterations of all rays.
    pub iterations: u64,
    /// Most iterations of one ray.
    pub max_iterations: u32,
}

/// What [`GpuTracer::render`] returns.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOutput {
    /// One hit per pixel, rows from the top; `t` in world units along the
    /// unit view ray. The attribute index is computed when asked for.
    pub hits: Vec<Hit>,
    /// RGBA8 pixels, rows from the top, shaded like the CPU renderer's
    /// `Shade::Normal`.
    pub rgba: Vec<u8>,
}

/// A DAG on the GPU, ready to trace.
#[derive(Debug)]
pub struct GpuTracer {
    context: GpuContext,
    pipelines: Arc<Pipelines>,
    /// Keeps the page buffers alive for the bind group.
    _pages: Vec<wgpu::Buffer>,
    pages_group: wgpu::BindGroup,
    frame: Frame,
    base_params: GpuParams,
    options: GpuOptions,
    page_count: u32,
    page_bytes: u64,
    total_bytes: u64,
    /// How the shader was specialised (the lit passes compile the same).
    config: ShaderConfig,
    /// The lit render's passes, compiled on first use (`lit.rs`).
    lit: std::sync::OnceLock<Result<Arc<lit::LitPipelines>, GpuError>>,
    /// The batch path's GPU buffers, kept between calls (`batch.rs`).
    slots: Mutex<batch::Slots>,
    /// The file's colour section on the device, when asked for (`colors.rs`).
    colors: Option<colors::SharedColors>,
    /// 2.0: how the node levels were uploaded (`None` for 1.0).
    v2_layout: Option<V2Layout>,
    /// 2.0 expanded: the time `dagfmt::expand::expand_levels` took.
    expansion_time: Option<Duration>,
}

/// What [`GpuTracer`]'s constructors hand to its upload: a DAG of either
/// format version, as the shader reads it.
struct DagSource<'a, 'b> {
    header: &'a dagfmt::Header,
    /// Whether the volume holds no voxel.
    empty: bool,
    levels: &'b [UploadLevel<'a>],
    /// The saturated-count table (level, node, count).
    saturated: Vec<(u8, u32, u64)>,
    /// Whether the levels are 2.0 (the shader variant to compile), and how
    /// they are laid out (`None` for 1.0).
    v2_layout: Option<V2Layout>,
    /// The file's colours, uploaded as stored when `GpuOptions::colors` asks.
    colors: Option<dagfmt::ColorTable<'a>>,
}

/// A compute shader's storage buffer binding.
pub(crate) fn storage(binding: u32, read_only: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

/// A compute shader's uniform buffer binding holding a `T`.
pub(crate) fn uniform<T>(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: wgpu::BufferSize::new(size_of::<T>() as u64),
        },
        count: None,
    }
}

impl GpuTracer {
    /// Makes a context ([`GpuContext::new`] with `options.adapter`) and
    /// uploads `dag`.
    pub fn new(dag: &Dag<'_>, options: &GpuOptions) -> Result<Self, GpuError> {
        Self::with_context(&GpuContext::new(options.adapter)?, dag, options)
    }

    /// Uploads `dag` to the device of `context`.
    pub fn with_context(
        context: &GpuContext,
        dag: &Dag<'_>,
        options: &GpuOptions,
    ) -> Result<Self, GpuError> {
        let saturated = upload::saturated_counts(dag)?;
        Self::build(
            context,
            DagSource {
                header: dag.header(),
                empty: dag.is_empty(),
                levels: &UploadLevel::v1(dag),
                saturated,
                v2_layout: None,
                colors: dag.color_table(),
            },
            options,
        )
    }

    /// Makes a context ([`GpuContext::new`] with `options.adapter`) and
    /// uploads a format 2.0 DAG (see [`GpuTracer::with_context_v2`]).
    pub fn new_v2(
        header: &dagfmt::Header,
        levels: &[LevelView<'_>],
        colors: Option<dagfmt::ColorTable<'_>>,
        options: &GpuOptions,
    ) -> Result<Self, GpuError> {
        Self::with_context_v2(
            &GpuContext::new(options.adapter)?,
            header,
            levels,
            colors,
            options,
        )
    }

    /// Uploads the level sections of a format 2.0 DAG (spec §23; root
    /// first, the leaf level last, as [`dagfmt::Dag2::levels`] or
    /// [`dagfmt::v2::Encoded::views`] give them) with `header`'s depth, root
    /// cube and attribute kind, to the device of `context`. The shader is
    /// the 2.0 variant (its own pipelines): it carries the accumulated
    /// reflection of §23.4, with the answers of the 1.0 file of the same
    /// voxels. With [`V2Layout::Expanded`] (the default) the node levels are
    /// expanded first (`dagfmt::expand::expand_levels`, spec §23.12) and the
    /// shader reads a child as one aligned word; where they do not expand,
    /// and with [`V2Layout::InPlace`], it decodes the records of §23.2 in
    /// place. Fails when the levels do not match the depth, a node level's
    /// widths are invalid (E070), or a level is more than 4 GiB (record
    /// offsets are 32-bit).
    pub fn with_context_v2(
        context: &GpuContext,
        header: &dagfmt::Header,
        levels: &[LevelView<'_>],
        colors: Option<dagfmt::ColorTable<'_>>,
        options: &GpuOptions,
    ) -> Result<Self, GpuError> {
        if levels.len() + 1 != usize::from(header.depth)
            || levels.last().is_some_and(|l| !l.is_leaf)
        {
            return Err(GpuError::InvalidOptions(format!(
                "{} 2.0 level sections for a DAG of depth {}",
                levels.len(),
                header.depth
            )));
        }
        for view in levels {
            if view.bytes.len() as u64 > u64::from(u32::MAX) {
                return Err(GpuError::TooLarge(format!(
                    "a 2.0 level of {} bytes is more than the shader addresses (4 GiB)",
                    view.bytes.len()
                )));
            }
            if !view.is_leaf && !view.bytes.is_empty() {
                dagfmt::v2::Coding::new(view.widths).map_err(GpuError::Malformed)?;
            }
        }
        let empty = levels[0].item_count == 0;
        if options.v2_layout == V2Layout::Expanded {
            let t0 = Instant::now();
            let expanded = dagfmt::expand::expand_levels(levels);
            let expansion_time = t0.elapsed();
            // A DAG that does not expand is traced in place (below), where
            // the shader meets its faults as it always did.
            if let Ok(expanded) = expanded {
                let words = upload::ExpandedWords::new(&expanded);
                let saturated = upload::saturated_counts_expanded(
                    &expanded,
                    levels[levels.len() - 1],
                    header.attribute_kind,
                    empty,
                )?;
                let mut tracer = Self::build(
                    context,
                    DagSource {
                        header,
                        empty,
                        levels: &UploadLevel::expanded(&words, levels),
                        saturated,
                        v2_layout: Some(V2Layout::Expanded),
                        colors,
                    },
                    options,
                )?;
                tracer.expansion_time = Some(expansion_time);
                return Ok(tracer);
            }
        }
        let saturated = upload::saturated_counts_v2(levels, header.attribute_kind)?;
        let starts = upload::record_starts(levels);
        Self::build(
            context,
            DagSource {
                header,
                empty,
                levels: &UploadLevel::v2(levels, &starts),
                saturated,
                v2_layout: Some(V2Layout::InPlace),
                colors,
            },
            options,
        )
    }

    /// Uploads the levels of `source` (of either format) and compiles the
    /// shader variant.
    fn build(
        context: &GpuContext,
        source: DagSource<'_, '_>,
        options: &GpuOptions,
    ) -> Result<Self, GpuError> {
        let DagSource {
            header,
            empty,
            levels,
            saturated,
            v2_layout,
            colors,
        } = source;
        let (stack_size, short_stack) = match options.stack {
            StackMode::Full => (MAX_STORED_LEVELS as u32, false),
            StackMode::Short(n) if n.is_power_of_two() && n <= 16 => (n, true),
            StackMode::Short(n) => {
                return Err(GpuError::InvalidOptions(format!(
                    "short stack of {n} entries: must be a power of two from 1 to 16"
                )));
            }
        };
        if options.rays_per_dispatch == 0
            || options.rays_per_dispatch > 65535 * BATCH_WORKGROUP_SIZE
        {
            return Err(GpuError::InvalidOptions(format!(
                "{} rays per dispatch: must be 1 to {}",
                options.rays_per_dispatch,
                65535 * BATCH_WORKGROUP_SIZE
            )));
        }
        let device_cap = context.max_binding_bytes();
        let cap = options
            .max_binding_bytes
            .map_or(device_cap, |b| b.min(device_cap));
        if cap < 16 {
            return Err(GpuError::InvalidOptions(format!(
                "a binding of {cap} bytes is too small"
            )));
        }
        let placement = Placement::new(levels, saturated, cap, context.max_pages().max(1))?;
        let config = ShaderConfig {
            stack_size,
            short_stack,
            pages: placement.pages,
            page_shift: placement.page_shift(),
            format_v2: v2_layout.is_some(),
            expanded: v2_layout == Some(V2Layout::Expanded),
        };
        let pipelines = context.pipelines(config)?;
        let device = &context.inner.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let pages: Vec<wgpu::Buffer> = (0..placement.pages)
            .map(|page| {
                device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("vdag page"),
                    size: placement.page_bytes(page),
                    usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                })
            })
            .collect();
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::TooLarge(e.to_string()));
        }
        upload::upload(device, &context.inner.queue, &placement, levels, &pages)?;
        let entries: Vec<wgpu::BindGroupEntry> = pages
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: b.as_entire_binding(),
            })
            .collect();
        let pages_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("vdag pages"),
            layout: &pipelines.pages_layout,
            entries: &entries,
        });
        let depth = header.depth;
        let indexed = options.compute_index && header.attribute_kind == AttributeKind::VoxelCount;
        let gpu_colors = match colors {
            Some(table) if options.colors && indexed => {
                Some(Arc::new(colors::GpuColors::new(context, table, cap)?))
            }
            _ => None,
        };
        let frame = Frame {
            depth,
            root_min: header.root_min,
            grid_scale: (1u64 << depth) as f64 / header.root_size,
            empty,
            indexed,
        };
        // Each node of a level is entered at most a few times per cell the ray
        // crosses on that level (about 3 * 2^level cells); a short stack
        // replays at most `depth` entries per return.
        let default_limit =
            (64u64 << depth).saturating_mul(if short_stack { u64::from(depth) } else { 1 });
        let max_iterations = options
            .max_iterations
            .unwrap_or(default_limit.min(u64::from(u32::MAX)) as u32);
        let base_params = GpuParams {
            depth: u32::from(depth),
            leaf_level: u32::from(depth - 2),
            ray_count: 0,
            max_iterations,
            sat_base: placement.sat_base,
            sat_count: placement.saturated.len() as u32,
            options: if indexed { OPTION_INDEX } else { 0 },
            render_level: u32::from(depth),
            width: 0,
            height: 0,
            empty: u32::from(empty),
            pad0: 0,
            cam_origin: [0.0; 4],
            cam_forward: [0.0; 4],
            cam_right: [0.0; 4],
            cam_up: [0.0; 4],
            levels: placement.levels,
        };
        Ok(GpuTracer {
            context: context.clone(),
            pipelines,
            _pages: pages,
            pages_group,
            frame,
            base_params,
            options: options.clone(),
            page_count: placement.pages,
            page_bytes: placement.page_words * 4,
            total_bytes: placement.total_words * 4,
            config,
            lit: std::sync::OnceLock::new(),
            slots: Mutex::new(batch::Slots::default()),
            colors: gpu_colors,
            v2_layout,
            expansion_time: None,
        })
    }

    /// The context (device) this tracer runs on.
    pub fn context(&self) -> &GpuContext {
        &self.context
    }

    /// Storage bindings the DAG is spread over.
    pub fn binding_count(&self) -> u32 {
        self.page_count
    }

    /// Bytes per binding (the last may be smaller).
    pub fn binding_bytes(&self) -> u64 {
        self.page_bytes
    }

    /// Bytes uploaded: the level sections (2.0: as laid out, expanded or
    /// with their record-start bit vectors) and the saturated-count table.
    pub fn uploaded_bytes(&self) -> u64 {
        self.total_bytes
    }

    /// How a 2.0 DAG's node levels were uploaded: [`V2Layout::InPlace`]
    /// when asked for or when they did not expand; `None` for a 1.0 DAG.
    pub fn v2_layout(&self) -> Option<V2Layout> {
        self.v2_layout
    }

    /// The time `dagfmt::expand::expand_levels` took, when the 2.0 DAG was
    /// uploaded expanded.
    pub fn expansion_time(&self) -> Option<Duration> {
        self.expansion_time
    }

    /// The loop iteration bound of one ray.
    pub fn max_iterations(&self) -> u32 {
        self.base_params.max_iterations
    }

    /// Traces every ray (see the module documentation for how its answers
    /// relate to [`crate::Tracer::trace_batch`]'s). Fails on the first ray
    /// whose level is deeper than the DAG, that exceeds the iteration limit,
    /// or that meets a pointer outside its level.
    pub fn trace(&self, rays: &[Ray]) -> Result<Vec<Hit>, GpuError> {
        self.trace_with_stats(rays).map(|(hits, _)| hits)
    }

    /// [`GpuTracer::trace`] with timings and iteration counts.
    pub fn trace_with_stats(&self, rays: &[Ray]) -> Result<(Vec<Hit>, TraceStats), GpuError> {
        let mut hits = vec![Hit::MISS; rays.len()];
        let stats = self.trace_into_with_stats(rays, &mut hits)?;
        Ok((hits, stats))
    }

    /// Uniform buffer with `params`.
    fn params_buffer(&self, params: &GpuParams) -> wgpu::Buffer {
        self.context
            .inner
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("vdag params"),
                contents: bytemuck::bytes_of(params),
                usage: wgpu::BufferUsages::UNIFORM,
            })
    }

    fn io_group(
        &self,
        params: &wgpu::Buffer,
        rays: &wgpu::Buffer,
        hits: &wgpu::Buffer,
        image: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        self.context
            .inner
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("vdag io"),
                layout: &self.context.inner.io_layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: BINDING_PARAMS,
                        resource: params.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: BINDING_RAYS,
                        resource: rays.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: BINDING_HITS,
                        resource: hits.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: BINDING_IMAGE,
                        resource: image.as_entire_binding(),
                    },
                ],
            })
    }

    /// Camera parameters in grid space.
    fn camera_params(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
        level: Option<u8>,
    ) -> Result<GpuParams, GpuError> {
        camera.frame()?;
        if width == 0
            || height == 0
            || width.div_ceil(RENDER_TILE) > 65535
            || height.div_ceil(RENDER_TILE) > 65535
        {
            return Err(GpuError::InvalidOptions(format!(
                "cannot render a {width} x {height} image"
            )));
        }
        let depth = self.frame.depth;
        let level = match level {
            None => depth,
            Some(l) if (1..=depth).contains(&l) => l,
            Some(l) => {
                return Err(GpuError::LevelTooDeep {
                    ray: 0,
                    level: l,
                    depth,
                });
            }
        };
        // The same frame as `Camera::frame` (which keeps its fields private).
        let origin = DVec3::from_array(camera.position);
        let forward = (DVec3::from_array(camera.look_at) - origin).normalize();
        let mut right = forward
            .cross(DVec3::from_array(camera.up))
            .normalize_or_zero();
        if right == DVec3::ZERO {
            right = forward.any_orthonormal_vector();
        }
        let up = right.cross(forward);
        let tan_half = (camera.fov_y_degrees.to_radians() * 0.5).tan();
        let aspect = f64::from(width) / f64::from(height);
        let grid = DVec3::from_array(std::array::from_fn(|i| {
            (camera.position[i] - self.frame.root_min[i]) * self.frame.grid_scale
        }));
        let v4 = |v: DVec3, w: f64| [v.x as f32, v.y as f32, v.z as f32, w as f32];
        Ok(GpuParams {
            ray_count: width * height,
            width,
            height,
            render_level: u32::from(level),
            cam_origin: v4(grid, 1.0 / self.frame.grid_scale),
            cam_forward: v4(forward, 0.0),
            cam_right: v4(right * tan_half * aspect, 0.0),
            cam_up: v4(up * tan_half, 0.0),
            ..self.base_params
        })
    }

    /// Records the render of `params` into `encoder`.
    fn encode_render(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        group: &wgpu::BindGroup,
        params: &GpuParams,
    ) {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: None,
            timestamp_writes: None,
        });
        pass.set_pipeline(&self.pipelines.render);
        pass.set_bind_group(0, group, &[]);
        pass.set_bind_group(1, &self.pages_group, &[]);
        pass.dispatch_workgroups(
            params.width.div_ceil(RENDER_TILE),
            params.height.div_ceil(RENDER_TILE),
            1,
        );
    }

    fn render_buffers(
        &self,
        pixels: u64,
        hits: bool,
        image: bool,
    ) -> Result<(wgpu::Buffer, wgpu::Buffer), GpuError> {
        let device = &self.context.inner.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let make = |label, size| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })
        };
        let hit_buffer = make(
            "vdag render hits",
            if hits {
                pixels * size_of::<GpuHit>() as u64
            } else {
                256
            },
        );
        let image_buffer = make("vdag image", if image { pixels * 4 } else { 256 });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Device(e.to_string()));
        }
        Ok((hit_buffer, image_buffer))
    }

    /// Renders a `width` x `height` image through `camera` at `level`
    /// (`None` = full depth), making the primary rays on the GPU (f32).
    pub fn render(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
        level: Option<u8>,
    ) -> Result<RenderOutput, GpuError> {
        let mut params = self.camera_params(camera, width, height, level)?;
        params.options |= OPTION_WRITE_HITS | OPTION_WRITE_IMAGE;
        let pixels = u64::from(width) * u64::from(height);
        let (hit_buffer, image_buffer) = self.render_buffers(pixels, true, true)?;
        let params_buffer = self.params_buffer(&params);
        let group = self.io_group(
            &params_buffer,
            &self.context.inner.dummy,
            &hit_buffer,
            &image_buffer,
        );
        let device = &self.context.inner.device;
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("vdag render"),
        });
        self.encode_render(&mut encoder, &group, &params);
        self.context.inner.queue.submit([encoder.finish()]);
        let raw: Vec<GpuHit> = self.context.read_back(&hit_buffer, pixels * 32)?;
        let rgba: Vec<u8> = self.context.read_back(&image_buffer, pixels * 4)?;
        let mut hits = Vec::with_capacity(raw.len());
        for (i, r) in raw.iter().enumerate() {
            let info = r.cell[3];
            if info & INFO_EXHAUSTED != 0 {
                return Err(GpuError::IterationLimit {
                    ray: i,
                    limit: params.max_iterations,
                });
            }
            if info & INFO_MALFORMED != 0 {
                return Err(GpuError::MalformedPointer { ray: i });
            }
            hits.push(if info & INFO_HIT == 0 {
                Hit::MISS
            } else {
                Hit {
                    hit: true,
                    t: r.t,
                    voxel: [r.cell[0], r.cell[1], r.cell[2]],
                    level: ((info >> INFO_LEVEL_SHIFT) & 0xff) as u8,
                    face: ((info >> INFO_FACE_SHIFT) & 0xff) as u8,
                    index: self
                        .frame
                        .indexed
                        .then_some(u64::from(r.index_lo) | u64::from(r.index_hi) << 32),
                }
            });
        }
        Ok(RenderOutput { hits, rgba })
    }

    /// Times `runs` renders of a `width` x `height` image (primary rays made
    /// and traced on the GPU, an RGBA image written, no attribute index, nothing
    /// read back): the wall time of each submission until the GPU is done.
    pub fn time_render(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
        runs: usize,
    ) -> Result<Vec<Duration>, GpuError> {
        let mut params = self.camera_params(camera, width, height, None)?;
        params.options = OPTION_WRITE_IMAGE;
        let (hit_buffer, image_buffer) =
            self.render_buffers(u64::from(width) * u64::from(height), false, true)?;
        let params_buffer = self.params_buffer(&params);
        let group = self.io_group(
            &params_buffer,
            &self.context.inner.dummy,
            &hit_buffer,
            &image_buffer,
        );
        let device = &self.context.inner.device;
        let mut times = Vec::with_capacity(runs);
        for _ in 0..runs {
            let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("vdag render"),
            });
            self.encode_render(&mut encoder, &group, &params);
            let t0 = Instant::now();
            self.context.inner.queue.submit([encoder.finish()]);
            self.context.wait()?;
            times.push(t0.elapsed());
        }
        Ok(times)
    }
}

#[cfg(test)]
mod color_check;
#[cfg(test)]
mod decode_check;
#[cfg(test)]
mod tests;
