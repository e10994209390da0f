//! The batch path: rays in, hits out, streamed through the GPU in chunks.
//!
//! A batch is cut into chunks of at most [`GpuOptions::rays_per_dispatch`]
//! rays, and two chunks are in flight at once, each in a [`Slot`] of GPU
//! buffers that is kept by the tracer between calls. While the GPU traces
//! chunk `k` (upload, dispatch and read-back copy in one submission), the
//! host sets chunk `k + 1` up, straight into the mapped upload buffer of the
//! other slot, on all cores; then it waits for chunk `k` and writes its
//! answers, again on all cores, from the mapped read-back buffer. So upload,
//! compute and read-back of one chunk overlap the host's work on the next,
//! and memory stays bounded by the two slots, whatever the batch size.
//!
//! The host's share per ray is the f64 set-up (`prepare.rs`, the CPU
//! tracer's operations, with the usual ray's case analysis folded into one
//! test: `prepare::setup_usual`, four rays at a time in AVX2 `f64` vectors
//! where the processor has it: `setup4.rs`) and copying the shader's answer
//! into a [`Hit`] (without a branch on whether the ray hit):
//! the shader computes the cell, the entry parameter, the face and the
//! attribute index. Only rare rays (see `prepare.rs`) have their answers
//! computed on the host.

use std::collections::VecDeque;
use std::ptr::NonNull;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::Receiver;
use std::time::{Duration, Instant};

use dagfmt::batch::{Hit, Ray};
use rayon::prelude::*;

use super::layout::{
    BATCH_WORKGROUP_SIZE, GpuHit, GpuParams, GpuRay, INFO_EXHAUSTED, INFO_FACE_SHIFT, INFO_HIT,
    INFO_HOST_ANSWER, INFO_LEVEL_SHIFT, INFO_MALFORMED, INFO_SKIPPED, RAY_SKIP,
};
use super::prepare::{self, Frame, Setup};
use super::{GpuError, GpuTracer, TraceStats, device_error};

/// What the shader gets for a ray answered on the host: it writes a record
/// marked [`INFO_SKIPPED`] for it and does nothing else.
const SKIPPED_RAY: GpuRay = GpuRay {
    origin: [0.0; 4],
    inv_dir: [0.0; 4],
    octant: 0,
    level: 0,
    flags: RAY_SKIP,
    scale_exponent: 0,
};

/// Rays one task of the parallel set-up and answer passes handles.
const TASK_RAYS: usize = 4096;

/// Chunks in flight at once: one traced while the next is set up.
const SLOTS: usize = 2;

/// The GPU buffers of one chunk in flight.
#[derive(Debug)]
pub(crate) struct Slot {
    /// Host-visible, written by the set-up while mapped.
    upload: wgpu::Buffer,
    /// The shader's rays.
    rays: wgpu::Buffer,
    /// The shader's answers.
    hits: wgpu::Buffer,
    /// Host-visible copy of the answers.
    read_back: wgpu::Buffer,
    params: wgpu::Buffer,
    group: wgpu::BindGroup,
    /// The pending mapping of `upload` for writing, after the submission
    /// that reads it (`None`: mapped at creation).
    upload_mapped: Option<(wgpu::SubmissionIndex, MapReceiver)>,
}

/// The slots of a tracer, made on the first batch and kept while no larger
/// chunk is asked for.
#[derive(Debug, Default)]
pub(crate) struct Slots {
    slots: Vec<Slot>,
    /// Rays each slot holds.
    capacity: usize,
}

/// The records of a mapped upload buffer, written by the set-up's tasks,
/// each its own range.
struct Records(NonNull<[u8; size_of::<GpuRay>()]>, usize);

// SAFETY: the pointer only serves to make write-only views of disjoint
// ranges, one per task, while the buffer stays mapped (`set_up_chunk`).
unsafe impl Send for Records {}
// SAFETY: as for `Send`: no task reads through it or writes another's range.
unsafe impl Sync for Records {}

/// Reports a buffer mapping.
type MapReceiver = Receiver<Result<(), wgpu::BufferAsyncError>>;

/// A chunk submitted to the GPU and not yet answered.
struct InFlight {
    /// Index of its first ray in the batch.
    first: usize,
    len: usize,
    slot: usize,
    submission: wgpu::SubmissionIndex,
    read_back: MapReceiver,
}

impl GpuTracer {
    fn make_slot(&self, capacity: usize) -> Result<Slot, GpuError> {
        let device = &self.context.inner.device;
        let ray_bytes = (capacity * size_of::<GpuRay>()) as u64;
        let hit_bytes = (capacity * size_of::<GpuHit>()) as u64;
        let scope = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let buffer = |label, size, usage, mapped_at_creation| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation,
            })
        };
        use wgpu::BufferUsages as U;
        let upload = buffer(
            "vdag ray upload",
            ray_bytes,
            U::MAP_WRITE | U::COPY_SRC,
            true,
        );
        let rays = buffer("vdag rays", ray_bytes, U::STORAGE | U::COPY_DST, false);
        let hits = buffer("vdag hits", hit_bytes, U::STORAGE | U::COPY_SRC, false);
        let read_back = buffer(
            "vdag hit read-back",
            hit_bytes,
            U::MAP_READ | U::COPY_DST,
            false,
        );
        let params = buffer(
            "vdag batch params",
            size_of::<GpuParams>() as u64,
            U::UNIFORM | U::COPY_DST,
            false,
        );
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Device(e.to_string()));
        }
        let group = self.io_group(&params, &rays, &hits, &self.context.inner.dummy);
        Ok(Slot {
            upload,
            rays,
            hits,
            read_back,
            params,
            group,
            upload_mapped: None,
        })
    }

    /// Traces every ray into `hits`, which must be as long as `rays` (see
    /// [`GpuTracer::trace`]): the batch path without a fresh answer vector,
    /// for callers that trace batch after batch.
    pub fn trace_into_with_stats(
        &self,
        rays: &[Ray],
        hits: &mut [Hit],
    ) -> Result<TraceStats, GpuError> {
        if rays.len() != hits.len() {
            return Err(GpuError::InvalidOptions(format!(
                "{} rays but room for {} hits",
                rays.len(),
                hits.len()
            )));
        }
        if rays.is_empty() {
            return Ok(TraceStats::default());
        }
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        let result = self.stream(&mut slots, rays, hits);
        if result.is_err() {
            // Chunks may be left mapped or in flight: start afresh next time.
            *slots = Slots::default();
        }
        result
    }

    /// [`GpuTracer::trace_into_with_stats`] with the slots locked.
    fn stream(
        &self,
        slots: &mut Slots,
        rays: &[Ray],
        hits: &mut [Hit],
    ) -> Result<TraceStats, GpuError> {
        let started = Instant::now();
        let mut stats = TraceStats::default();
        let chunk = self.options.rays_per_dispatch as usize;
        let wanted = chunk
            .min(rays.len())
            .next_multiple_of(BATCH_WORKGROUP_SIZE as usize);
        if slots.capacity < wanted {
            // Free the old ones first: they may be large.
            slots.slots.clear();
            slots.capacity = 0;
            for _ in 0..SLOTS {
                let slot = self.make_slot(wanted)?;
                slots.slots.push(slot);
            }
            slots.capacity = wanted;
        }
        let slots = &mut slots.slots;
        let mut host = Duration::ZERO;
        let mut in_flight: VecDeque<InFlight> = VecDeque::new();
        let mut first_submit = None;
        for (index, first) in (0..rays.len()).step_by(chunk).enumerate() {
            let len = chunk.min(rays.len() - first);
            let slot = index % SLOTS;
            if in_flight.len() == SLOTS {
                let done = in_flight.pop_front().expect("a chunk in flight");
                self.answer_chunk(&slots[done.slot], done, rays, hits, &mut stats, &mut host)?;
            }
            let t0 = Instant::now();
            self.set_up_chunk(
                &mut slots[slot],
                &rays[first..first + len],
                &mut hits[first..first + len],
                first,
            )?;
            host += t0.elapsed();
            let submission = self.submit_chunk(&slots[slot], len);
            first_submit.get_or_insert_with(Instant::now);
            in_flight.push_back(InFlight {
                first,
                len,
                slot,
                submission: submission.clone(),
                read_back: map_read(&slots[slot].read_back, (len * size_of::<GpuHit>()) as u64),
            });
            slots[slot].upload_mapped = Some((submission, map_write(&slots[slot].upload)));
        }
        let mut gpu_done = Instant::now();
        while let Some(done) = in_flight.pop_front() {
            let slot = done.slot;
            gpu_done = self.answer_chunk(&slots[slot], done, rays, hits, &mut stats, &mut host)?;
        }
        stats.gpu_time = first_submit.map_or(Duration::ZERO, |t| gpu_done - t);
        stats.host_time = host;
        stats.total_time = started.elapsed();
        Ok(stats)
    }

    /// Sets the rays of one chunk up into the slot's upload buffer (on all
    /// cores) and unmaps it; answers the rays that need no DAG into `hits`.
    fn set_up_chunk(
        &self,
        slot: &mut Slot,
        rays: &[Ray],
        hits: &mut [Hit],
        first: usize,
    ) -> Result<(), GpuError> {
        if let Some((submission, mapped)) = slot.upload_mapped.take() {
            self.wait_for(submission, &mapped)?;
        }
        let bytes = (rays.len() * size_of::<GpuRay>()) as u64;
        let mut view = slot
            .upload
            .get_mapped_range_mut(..bytes)
            .map_err(device_error)?;
        let (mut records, _) = view.slice(..).into_chunks::<{ size_of::<GpuRay>() }>();
        let records = &Records(records.as_raw_element_ptr(), records.len());
        let too_deep = AtomicUsize::new(usize::MAX);
        let lanes = lanes_available();
        rays.par_chunks(TASK_RAYS)
            .zip(hits.par_chunks_mut(TASK_RAYS))
            .enumerate()
            .for_each(|(task, (rays, hits))| {
                let first = task * TASK_RAYS;
                assert!(first + rays.len() <= records.1, "records for every ray");
                // SAFETY: `records` points to `records.1` records of the
                // mapped upload buffer, which `view` keeps mapped until after
                // this pass; each task makes a write-only view of its own
                // range of them (`first..first + rays.len()`, within bounds
                // by the assertion), disjoint from every other task's.
                let out: wgpu::WriteOnly<'_, [[u8; size_of::<GpuRay>()]]> = unsafe {
                    wgpu::WriteOnly::new(NonNull::slice_from_raw_parts(
                        records.0.add(first),
                        rays.len(),
                    ))
                };
                if let Some(k) = set_up_task(&self.frame, rays, hits, out, lanes) {
                    too_deep.fetch_min(first + k, Ordering::Relaxed);
                }
            });
        drop(view);
        slot.upload.unmap();
        let i = too_deep.into_inner();
        if let Some(Err(prepare::LevelTooDeep(level))) =
            rays.get(i).map(|ray| prepare::setup(&self.frame, ray))
        {
            return Err(GpuError::LevelTooDeep {
                ray: first + i,
                level,
                depth: self.frame.depth,
            });
        }
        Ok(())
    }

    /// Submits one chunk: upload copy, dispatch, read-back copy.
    fn submit_chunk(&self, slot: &Slot, len: usize) -> wgpu::SubmissionIndex {
        let inner = &self.context.inner;
        let params = GpuParams {
            ray_count: len as u32,
            ..self.base_params
        };
        inner
            .queue
            .write_buffer(&slot.params, 0, bytemuck::bytes_of(&params));
        let mut encoder = inner
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("vdag batch"),
            });
        let ray_bytes = (len * size_of::<GpuRay>()) as u64;
        let hit_bytes = (len * size_of::<GpuHit>()) as u64;
        encoder.copy_buffer_to_buffer(&slot.upload, 0, &slot.rays, 0, ray_bytes);
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: None,
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipelines.batch);
            pass.set_bind_group(0, &slot.group, &[]);
            pass.set_bind_group(1, &self.pages_group, &[]);
            pass.dispatch_workgroups((len as u32).div_ceil(BATCH_WORKGROUP_SIZE), 1, 1);
        }
        encoder.copy_buffer_to_buffer(&slot.hits, 0, &slot.read_back, 0, hit_bytes);
        inner.queue.submit([encoder.finish()])
    }

    /// Waits for `submission` and then for the mapping `mapped` requested
    /// after it, without waiting for later submissions (those of the next
    /// chunk), unless the mapping is still not reported.
    fn wait_for(
        &self,
        submission: wgpu::SubmissionIndex,
        mapped: &MapReceiver,
    ) -> Result<(), GpuError> {
        self.context
            .inner
            .device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(submission),
                timeout: None,
            })
            .map_err(device_error)?;
        loop {
            match mapped.try_recv() {
                Ok(result) => return result.map_err(device_error),
                Err(std::sync::mpsc::TryRecvError::Empty) => self.context.wait()?,
                Err(e) => return Err(device_error(e)),
            }
        }
    }

    /// Waits for a chunk and writes its answers (on all cores). Returns
    /// when the wait for the GPU ended.
    fn answer_chunk(
        &self,
        slot: &Slot,
        done: InFlight,
        rays: &[Ray],
        hits: &mut [Hit],
        stats: &mut TraceStats,
        host: &mut Duration,
    ) -> Result<Instant, GpuError> {
        self.wait_for(done.submission.clone(), &done.read_back)?;
        let t0 = Instant::now();
        let range = done.first..done.first + done.len;
        let view = slot
            .read_back
            .get_mapped_range(..(done.len * size_of::<GpuHit>()) as u64)
            .map_err(device_error)?;
        let frame = &self.frame;
        let (traced, iterations, most, fault) = view
            .par_chunks(TASK_RAYS * size_of::<GpuHit>())
            .zip(rays[range.clone()].par_chunks(TASK_RAYS))
            .zip(hits[range].par_chunks_mut(TASK_RAYS))
            .enumerate()
            .map(|(task, ((records, rays), hits))| {
                let mut sums = (0u64, 0u64, 0u32, None);
                for (k, ((record, ray), hit)) in records
                    .chunks_exact(size_of::<GpuHit>())
                    .zip(rays)
                    .zip(hits)
                    .enumerate()
                {
                    let r: GpuHit = bytemuck::pod_read_unaligned(record);
                    let info = r.cell[3];
                    if info & (INFO_SKIPPED | INFO_EXHAUSTED | INFO_MALFORMED | INFO_HOST_ANSWER)
                        != 0
                    {
                        // Rare: answered on the host, a fault, or `t` and
                        // the face left to the host.
                        if info & INFO_SKIPPED != 0 {
                            continue;
                        }
                        sums.0 += 1;
                        sums.1 += u64::from(r.iterations);
                        sums.2 = sums.2.max(r.iterations);
                        if info & (INFO_EXHAUSTED | INFO_MALFORMED) != 0 {
                            sums.3 = sums.3.or(Some((task * TASK_RAYS + k, info)));
                        }
                        *hit = rare_answer(frame, ray, &r);
                        continue;
                    }
                    sums.0 += 1;
                    sums.1 += u64::from(r.iterations);
                    sums.2 = sums.2.max(r.iterations);
                    *hit = usual_answer(frame, &r);
                }
                sums
            })
            .reduce(
                || (0, 0, 0, None),
                |a, b| {
                    let fault = match (a.3, b.3) {
                        (Some(x), Some(y)) => Some(if x.0 <= y.0 { x } else { y }),
                        (x, y) => x.or(y),
                    };
                    (a.0 + b.0, a.1 + b.1, a.2.max(b.2), fault)
                },
            );
        drop(view);
        slot.read_back.unmap();
        *host += t0.elapsed();
        stats.gpu_rays += traced;
        stats.iterations += iterations;
        stats.max_iterations = stats.max_iterations.max(most);
        if let Some((i, info)) = fault {
            return Err(if info & INFO_EXHAUSTED != 0 {
                GpuError::IterationLimit {
                    ray: done.first + i,
                    limit: self.base_params.max_iterations,
                }
            } else {
                GpuError::MalformedPointer {
                    ray: done.first + i,
                }
            });
        }
        Ok(t0)
    }
}

/// Sets the rays of one task of [`GpuTracer::set_up_chunk`] up into `out`
/// (one record a ray), answering those that need no DAG into `hits`: four
/// at a time with [`setup4::setup4`](super::setup4::setup4) where `lanes`
/// (the processor has AVX2), otherwise one by one with
/// [`prepare::setup_usual`], and the rays these decline with
/// [`prepare::setup`]. Returns the first ray whose level is deeper than the
/// DAG.
fn set_up_task(
    frame: &Frame,
    rays: &[Ray],
    hits: &mut [Hit],
    mut out: wgpu::WriteOnly<'_, [[u8; size_of::<GpuRay>()]]>,
    lanes: bool,
) -> Option<usize> {
    assert!(out.len() == rays.len() && hits.len() == rays.len());
    let records = out.as_raw_element_ptr();
    let mut too_deep = None;
    // Sets ray `k` up on its own.
    let mut one = |k: usize, hit: &mut Hit| {
        let ray = &rays[k];
        let gpu = match prepare::setup_usual(frame, ray) {
            Some(gpu) => gpu,
            None => match prepare::setup(frame, ray) {
                Ok(Setup::Trace(gpu)) => gpu,
                Ok(Setup::Done(answer)) => {
                    *hit = answer;
                    SKIPPED_RAY
                }
                Err(_) => {
                    too_deep = too_deep.or(Some(k));
                    SKIPPED_RAY
                }
            },
        };
        // SAFETY: `k < rays.len() == out.len()`: a record of `out`, which
        // this task alone writes (and never reads).
        unsafe { records.add(k).write(bytemuck::cast(gpu)) };
    };
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if lanes {
        for (block, hits) in rays.chunks_exact(4).zip(hits.chunks_exact_mut(4)) {
            let block: &[Ray; 4] = block.try_into().expect("four rays");
            // SAFETY: `lanes` is only set where the processor has AVX2, and
            // records `done .. done + 4` lie within `out` (`done + 4 <=
            // rays.len() == out.len()`), written by this task alone.
            let usual =
                unsafe { super::setup4::setup4(frame, block, records.add(done).as_ptr().cast()) };
            if usual != 0b1111 {
                for (lane, hit) in hits.iter_mut().enumerate() {
                    if usual & (1 << lane) == 0 {
                        one(done + lane, hit);
                    }
                }
            }
            done += 4;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = lanes;
    for (k, hit) in hits.iter_mut().enumerate().skip(done) {
        one(k, hit);
    }
    too_deep
}

/// The answer for a shader's record `r` with neither [`INFO_SKIPPED`],
/// [`INFO_EXHAUSTED`], [`INFO_MALFORMED`] nor [`INFO_HOST_ANSWER`]: a hit
/// with the shader's `t` and face, or [`Hit::MISS`]. Without a branch on
/// whether the ray hit (which random rays would mispredict half the time):
/// every field is masked by the hit bit.
#[inline(always)]
fn usual_answer(frame: &Frame, r: &GpuHit) -> Hit {
    let info = r.cell[3];
    let hit = info & INFO_HIT != 0;
    let keep = 0u32.wrapping_sub(info & INFO_HIT);
    let index = u64::from(r.index_lo) | u64::from(r.index_hi) << 32;
    Hit {
        hit,
        t: f32::from_bits(r.t.to_bits() & keep),
        voxel: [r.cell[0] & keep, r.cell[1] & keep, r.cell[2] & keep],
        level: ((info & keep) >> INFO_LEVEL_SHIFT) as u8,
        face: ((info & keep) >> INFO_FACE_SHIFT) as u8,
        index: (frame.indexed & hit).then_some(index),
    }
}

/// The answer for a shader's record `r` of `ray` that [`usual_answer`]
/// does not take (and not [`INFO_SKIPPED`]): `t` and the face computed on
/// the host when the record says so.
#[cold]
fn rare_answer(frame: &Frame, ray: &Ray, r: &GpuHit) -> Hit {
    let info = r.cell[3];
    if info & INFO_HIT == 0 {
        return Hit::MISS;
    }
    let level = ((info >> INFO_LEVEL_SHIFT) & 0xff) as u8;
    let voxel = [r.cell[0], r.cell[1], r.cell[2]];
    let (t, face) = if info & INFO_HOST_ANSWER != 0 {
        prepare::host_answer(frame, ray, voxel, level)
    } else {
        (r.t, ((info >> INFO_FACE_SHIFT) & 0xff) as u8)
    };
    Hit {
        hit: true,
        t,
        voxel,
        level,
        face,
        index: frame
            .indexed
            .then_some(u64::from(r.index_lo) | u64::from(r.index_hi) << 32),
    }
}

/// Whether the set-up can take four rays at a time (`setup4.rs`).
fn lanes_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    return super::setup4::available();
    #[cfg(not(target_arch = "x86_64"))]
    return false;
}

/// Maps the first `size` bytes of `buffer` for reading once the GPU is done with it.
fn map_read(buffer: &wgpu::Buffer, size: u64) -> MapReceiver {
    let (sender, receiver) = std::sync::mpsc::channel();
    buffer.map_async(wgpu::MapMode::Read, ..size, move |r| {
        let _ = sender.send(r);
    });
    receiver
}

/// Maps `buffer` for writing once the GPU is done with it.
fn map_write(buffer: &wgpu::Buffer) -> MapReceiver {
    let (sender, receiver) = std::sync::mpsc::channel();
    buffer.map_async(wgpu::MapMode::Write, .., move |r| {
        let _ = sender.send(r);
    });
    receiver
}

#[cfg(test)]
mod tests {
    use super::super::prepare::tests::{frames, random_ray};
    use super::*;

    /// A task's set-up four lanes at a time writes the records and answers
    /// of the set-up one ray at a time, byte for byte, and finds the same
    /// first ray too deep, on hostile rays (and a tail shorter than four).
    #[test]
    fn set_up_task_with_lanes_is_the_one_by_one_set_up() {
        if !lanes_available() {
            eprintln!("no AVX2 here: the four-lane set-up is not used, nothing to check");
            return;
        }
        let mut state = 5u64;
        for frame in frames() {
            let rays: Vec<Ray> = (0..40_003)
                .map(|_| random_ray(&mut state, &frame))
                .collect();
            let run = |lanes: bool| {
                let mut records = vec![[0x5au8; size_of::<GpuRay>()]; rays.len()];
                let mut hits = vec![Hit::MISS; rays.len()];
                let too_deep = set_up_task(
                    &frame,
                    &rays,
                    &mut hits,
                    wgpu::WriteOnly::from_mut(&mut records[..]),
                    lanes,
                );
                (records, format!("{hits:?}"), too_deep)
            };
            let (one, lanes) = (run(false), run(true));
            assert!(one.2.is_some(), "some rays are too deep");
            assert_eq!(one.2, lanes.2);
            for (k, (a, b)) in one.0.iter().zip(&lanes.0).enumerate() {
                assert_eq!(a, b, "{:?} in {frame:?}", rays[k]);
            }
            assert!(one.1 == lanes.1, "answers differ in {frame:?}");
        }
    }

    /// The branch-free answer is the one with branches (`rare_answer`, the
    /// answer as it always was) for every record it takes, hit or miss,
    /// whatever the rest of the record holds, with and without the index.
    #[test]
    fn usual_answer_is_the_branching_one() {
        let mut state = 3u64;
        let mut next = || {
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        };
        let ray = Ray::new([0.0; 3], [1.0; 3]);
        for indexed in [false, true] {
            let frame = Frame {
                indexed,
                ..frames()[0]
            };
            for _ in 0..100_000 {
                let bits = next();
                let info = (bits as u32 & INFO_HIT)
                    | (((bits >> 8) & 0xff) as u32) << INFO_LEVEL_SHIFT
                    | (((bits >> 16) % 7) as u32) << INFO_FACE_SHIFT;
                let r = GpuHit {
                    cell: [next() as u32, next() as u32, next() as u32, info],
                    t: f32::from_bits(next() as u32),
                    index_lo: next() as u32,
                    index_hi: next() as u32,
                    iterations: next() as u32,
                };
                assert_eq!(
                    format!("{:?}", usual_answer(&frame, &r)),
                    format!("{:?}", rare_answer(&frame, &ray, &r)),
                    "{r:?}"
                );
            }
        }
    }
}
