//! Voxel colours on the GPU: the file's colour section in storage buffers,
//! as it is in the file, and the colour pass (`colors.wgsl`) that looks a
//! record's colour up by its attribute index.
//!
//! The GPU holds the section's bytes as little-endian 32-bit words, not a
//! decoded copy: a PACKED_COLORS section (spec §12.6) is decoded in WGSL,
//! colour by colour, from its directory and blocks; a VOXEL_COLORS section
//! (§12.5) is one word per colour. Both take the same path. A section larger
//! than one storage binding is cut into pages of a power-of-two number of
//! words, as the DAG's words are (`upload.rs`); one that needs more bindings
//! than the device has, or 4 GiB or more, is refused with
//! [`GpuError::TooLarge`].
//!
//! The pass reads records (the render's hits, the lit render's surfaces, or
//! indices the host uploads) from a storage buffer with a stride and the
//! word offsets of their info bits and index ([`GpuColorParams`]), and
//! writes two words a record: the RGBA8 colour and whether there is one.

use std::sync::Arc;

use bytemuck::Zeroable as _;
use dagfmt::ColorTable;
use dagfmt::batch::Hit;
use wgpu::util::DeviceExt as _;

use super::layout::{
    self, BINDING_COLOR_OUT, BINDING_COLOR_PAGES, BINDING_COLOR_PARAMS, BINDING_COLOR_RECORDS,
    COLOR_DISPATCH_ROW, COLOR_IO_STORAGE_BUFFERS, COLOR_WORKGROUP_SIZE, ColorConfig,
    GpuColorParams, MAX_PAGES,
};
use super::upload::PageWriter;
use super::{GpuContext, GpuError, GpuTracer, device_error, storage, uniform};

/// Records of one dispatch of [`GpuTracer::hit_colors`].
const CHUNK_RECORDS: usize = 1 << 20;

/// A colour section on the device with its compiled pass.
#[derive(Debug)]
pub(crate) struct GpuColors {
    /// How the pass is specialised.
    pub config: ColorConfig,
    /// The section's words, page after page.
    pages: Vec<wgpu::Buffer>,
    /// The section's part of the parameters (the records' part is per call).
    base: GpuColorParams,
    pipeline: Arc<ColorPipeline>,
    /// Bytes uploaded.
    pub bytes: u64,
}

/// Where the records' info bits and index lie, in words.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RecordShape {
    pub stride: u32,
    pub info_word: u32,
    pub index_word: u32,
    pub info_mask: u32,
}

impl GpuColors {
    /// Uploads `table` (the colours of `count` voxels) to the device of
    /// `context`, in pages of at most `cap` bytes.
    pub fn new(context: &GpuContext, table: ColorTable<'_>, cap: u64) -> Result<Self, GpuError> {
        let (bytes, packed, base) = match table {
            ColorTable::Raw(b) => (
                b,
                false,
                GpuColorParams {
                    colors: u32::try_from(b.len() / 4).map_err(|_| too_many(b.len() as u64 / 4))?,
                    ..GpuColorParams::zeroed()
                },
            ),
            ColorTable::Packed(p) => {
                let trailer = p.trailer();
                let too_big = || {
                    GpuError::TooLarge(format!(
                        "the PACKED_COLORS section's {} bytes exceed the colour pass's 32-bit byte offsets (4 GiB)",
                        p.bytes().len()
                    ))
                };
                if p.bytes().len() as u64 >= 1 << 32 {
                    return Err(too_big());
                }
                (
                    p.bytes(),
                    true,
                    GpuColorParams {
                        colors: u32::try_from(p.len()).map_err(|_| too_many(p.len()))?,
                        error_bound: u32::from(trailer.error_bound),
                        block_shift: u32::from(trailer.layout.shift),
                        split: u32::from(trailer.layout.split),
                        offset_bits: trailer.layout.offset_bits(),
                        directory: u32::try_from(p.directory_offset()).map_err(|_| too_big())?,
                        ..GpuColorParams::zeroed()
                    },
                )
            }
        };
        let total_words = (bytes.len() as u64).div_ceil(4).max(4);
        let cap_words = (cap / 4).max(4);
        let (page_words, pages) = if total_words <= cap_words {
            (total_words, 1)
        } else {
            let page_words = 1u64 << (63 - cap_words.leading_zeros());
            (page_words, total_words.div_ceil(page_words))
        };
        let inner = &context.inner;
        let max_pages = inner
            .limits
            .max_storage_buffers_per_shader_stage
            .saturating_sub(COLOR_IO_STORAGE_BUFFERS)
            .min(MAX_PAGES);
        if pages > u64::from(max_pages) {
            return Err(GpuError::TooLarge(format!(
                "the colour section's {} bytes need {pages} storage bindings of {} bytes; the device allows {max_pages}",
                bytes.len(),
                page_words * 4
            )));
        }
        let config = ColorConfig {
            packed,
            pages: pages as u32,
            page_shift: page_words.trailing_zeros(),
        };
        let device = &inner.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let buffers: Vec<wgpu::Buffer> = (0..pages)
            .map(|page| {
                let words = (total_words - page * page_words).min(page_words).max(4);
                device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("vdag colour page"),
                    size: words * 4,
                    usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                })
            })
            .collect();
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::TooLarge(e.to_string()));
        }
        let mut writer = PageWriter::new(device, &inner.queue, page_words, &buffers);
        writer.write(0, bytes)?;
        writer.flush()?;
        let pipeline = ColorPipeline::get(context, config)?;
        Ok(GpuColors {
            config,
            pages: buffers,
            base,
            pipeline,
            bytes: bytes.len() as u64,
        })
    }

    /// Records the pass over `count` records of shape `shape` in `records`
    /// into `encoder`, writing two words a record into `out`.
    pub fn encode(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        records: &wgpu::Buffer,
        count: u32,
        shape: RecordShape,
        out: &wgpu::Buffer,
    ) {
        if count == 0 {
            return;
        }
        let device = &context.inner.device;
        let params = GpuColorParams {
            count,
            stride: shape.stride,
            info_word: shape.info_word,
            index_word: shape.index_word,
            info_mask: shape.info_mask,
            ..self.base
        };
        let params = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("vdag colour params"),
            contents: bytemuck::bytes_of(&params),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let mut entries = vec![
            wgpu::BindGroupEntry {
                binding: BINDING_COLOR_PARAMS,
                resource: params.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: BINDING_COLOR_RECORDS,
                resource: records.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: BINDING_COLOR_OUT,
                resource: out.as_entire_binding(),
            },
        ];
        for (i, page) in self.pages.iter().enumerate() {
            entries.push(wgpu::BindGroupEntry {
                binding: BINDING_COLOR_PAGES + i as u32,
                resource: page.as_entire_binding(),
            });
        }
        let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("vdag colours"),
            layout: &self.pipeline.layout,
            entries: &entries,
        });
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("vdag colours"),
            timestamp_writes: None,
        });
        pass.set_pipeline(&self.pipeline.pipeline);
        pass.set_bind_group(layout::GROUP_COLORS, &group, &[]);
        let groups = count.div_ceil(COLOR_WORKGROUP_SIZE);
        let x = groups.min(COLOR_DISPATCH_ROW);
        pass.dispatch_workgroups(x, groups.div_ceil(x), 1);
    }

    /// Runs the pass over `count` records of shape `shape` in `records` and
    /// reads its output back (two words a record).
    pub fn decode(
        &self,
        context: &GpuContext,
        records: &wgpu::Buffer,
        count: u32,
        shape: RecordShape,
    ) -> Result<Vec<u32>, GpuError> {
        if count == 0 {
            return Ok(Vec::new());
        }
        let device = &context.inner.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let out = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("vdag colours out"),
            size: u64::from(count) * 8,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(device_error(e));
        }
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("vdag colours"),
        });
        self.encode(context, &mut encoder, records, count, shape, &out);
        context.inner.queue.submit([encoder.finish()]);
        context.read_back(&out, u64::from(count) * 8)
    }
}

fn too_many(n: u64) -> GpuError {
    GpuError::TooLarge(format!(
        "{n} colours: the colour pass takes fewer than 2^32"
    ))
}

/// The compiled colour pass of one [`ColorConfig`], cached per context.
#[derive(Debug)]
pub(crate) struct ColorPipeline {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
}

impl ColorPipeline {
    /// The pass for `config`, compiled once per context.
    fn get(context: &GpuContext, config: ColorConfig) -> Result<Arc<Self>, GpuError> {
        let mut cache = context
            .inner
            .color_pipelines
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if let Some(p) = cache.get(&config) {
            return Ok(p.clone());
        }
        let p = Arc::new(compile(context, &config)?);
        cache.insert(config, p.clone());
        Ok(p)
    }
}

/// Compiles the colour pass for `config`.
fn compile(context: &GpuContext, config: &ColorConfig) -> Result<ColorPipeline, GpuError> {
    let device = &context.inner.device;
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("vdag colors.wgsl"),
        source: wgpu::ShaderSource::Wgsl(layout::color_shader_source(config).into()),
    });
    let mut entries = vec![
        uniform::<GpuColorParams>(BINDING_COLOR_PARAMS),
        storage(BINDING_COLOR_RECORDS, true),
        storage(BINDING_COLOR_OUT, false),
    ];
    entries.extend((0..config.pages).map(|p| storage(BINDING_COLOR_PAGES + p, true)));
    let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("vdag colours"),
        entries: &entries,
    });
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some("vdag colours"),
        bind_group_layouts: &[Some(&layout)],
        immediate_size: 0,
    });
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("record_colors"),
        layout: Some(&pipeline_layout),
        module: &module,
        entry_point: Some("record_colors"),
        compilation_options: Default::default(),
        cache: None,
    });
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(GpuError::Shader(e.to_string()));
    }
    Ok(ColorPipeline { layout, pipeline })
}

/// Colours from the pass's output words (two a record).
pub(crate) fn unpack(words: &[u32]) -> Vec<Option<[u8; 4]>> {
    words
        .chunks_exact(2)
        .map(|w| (w[1] != 0).then(|| w[0].to_le_bytes()))
        .collect()
}

impl GpuTracer {
    /// Whether the file's colours are on the device
    /// ([`super::GpuOptions::colors`] and a file with a colour section).
    pub fn has_colors(&self) -> bool {
        self.colors.is_some()
    }

    /// Bytes of the colour section on the device (0 without colours): the
    /// section as it is in the file, compressed or not.
    pub fn color_bytes(&self) -> u64 {
        self.colors.as_ref().map_or(0, |c| c.bytes)
    }

    /// Storage bindings the colour section is spread over (0 without colours).
    pub fn color_binding_count(&self) -> u32 {
        self.colors.as_ref().map_or(0, |c| c.config.pages)
    }

    /// The colours of the voxels with these dense indices, decoded on the
    /// device (`None` past the end of the section); an error without colours
    /// on the device.
    pub fn colors_of(&self, indices: &[u64]) -> Result<Vec<Option<[u8; 4]>>, GpuError> {
        let records: Vec<[u32; 3]> = indices
            .iter()
            .map(|&i| [1, i as u32, (i >> 32) as u32])
            .collect();
        self.record_colors(&records)
    }

    /// The colour of each hit's voxel, decoded on the device from the hit's
    /// attribute index (`None` for misses and hits without an index or past
    /// the section); an error without colours on the device. The indices go
    /// to the device in chunks, 12 bytes a hit.
    pub fn hit_colors(&self, hits: &[Hit]) -> Result<Vec<Option<[u8; 4]>>, GpuError> {
        let records: Vec<[u32; 3]> = hits
            .iter()
            .map(|h| match h.index {
                Some(i) if h.hit => [1, i as u32, (i >> 32) as u32],
                _ => [0; 3],
            })
            .collect();
        self.record_colors(&records)
    }

    /// Runs the pass over `(flag, index low, index high)` records.
    fn record_colors(&self, records: &[[u32; 3]]) -> Result<Vec<Option<[u8; 4]>>, GpuError> {
        let colors = self.gpu_colors()?;
        let device = &self.context.inner.device;
        let mut out = Vec::with_capacity(records.len());
        for chunk in records.chunks(CHUNK_RECORDS) {
            let buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("vdag colour records"),
                contents: bytemuck::cast_slice(chunk),
                usage: wgpu::BufferUsages::STORAGE,
            });
            let words = colors.decode(
                &self.context,
                &buffer,
                chunk.len() as u32,
                RecordShape {
                    stride: 3,
                    info_word: 0,
                    index_word: 1,
                    info_mask: 1,
                },
            )?;
            out.extend(unpack(&words));
        }
        Ok(out)
    }

    /// The colours on the device, or why there are none.
    pub(crate) fn gpu_colors(&self) -> Result<&GpuColors, GpuError> {
        self.colors.as_deref().ok_or_else(|| {
            GpuError::InvalidOptions(
                "the tracer holds no colours (GpuOptions::colors, and a file with a colour section)"
                    .into(),
            )
        })
    }
}

/// Keeps [`GpuColors`] shareable between a tracer and its passes.
pub(crate) type SharedColors = Arc<GpuColors>;
