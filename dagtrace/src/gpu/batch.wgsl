// The batch entry point: rays set up by the host (dagtrace/src/gpu/prepare.rs),
// traced with `traverse` (trace.wgsl), answered here.
//
// The entry parameter and face are computed as the CPU tracer's `found_from`
// computes them (dagtrace/src/walk.rs), from the same plane parameters:
// the latest slab start of the moving axes (ties to the lowest axis), or the
// segment's start with face 0 when that is earlier. The parameter is then
// scaled back by 2^-k, exactly (a power of two), to the ray as given. Rays
// that start inside the cell they hit, and rays the host flagged, leave `t`
// and the face to the host (INFO_HOST_ANSWER), which computes them in f64.

@compute @workgroup_size(BATCH_WORKGROUP_SIZE)
fn trace_batch(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.ray_count) {
        return;
    }
    let ray = rays[i];
    if ((ray.flags & RAY_SKIP) != 0u || params.empty != 0u) {
        var skipped = miss_record();
        skipped.cell.w = INFO_SKIPPED;
        hits[i] = skipped;
        return;
    }
    var p: Prepared;
    p.o = ray.origin.xyz;
    p.inv = ray.inv_dir.xyz;
    p.tmin = ray.origin.w;
    p.tmax = ray.inv_dir.w;
    p.neg = ray.octant;
    p.level = ray.level;
    let f = traverse(p);
    var h = hit_record(f, p.neg);
    if (f.hit) {
        if ((ray.flags & RAY_HOST_ANSWER) != 0u) {
            h.cell.w |= INFO_HOST_ANSWER;
        } else {
            let size = f32(1u << (params.depth - f.level));
            let t_lo = (vec3<f32>(f.cell) * size - p.o) * p.inv;
            let moving = (vec3<u32>(ray.flags >> RAY_MOVING_SHIFT) & vec3<u32>(1u, 2u, 4u)) != vec3<u32>(0u);
            let t = select(vec3<f32>(-PARAMETER_BOUND), t_lo, moving);
            // The first axis of the largest: x if x >= y and x >= z, else y
            // if y >= z, else z.
            var axis = 2u;
            if (t.x >= t.y && t.x >= t.z) {
                axis = 0u;
            } else if (t.y >= t.z) {
                axis = 1u;
            }
            let near = t[axis];
            if (near < p.tmin) {
                // Starts inside the cell: t is the segment's start, which the
                // shader only has clamped to PARAMETER_BOUND.
                h.cell.w |= INFO_HOST_ANSWER;
            } else {
                let face = 1u + 2u * axis + ((p.neg >> axis) & 1u);
                h.cell.w |= face << INFO_FACE_SHIFT;
                h.t = ldexp(near, -bitcast<i32>(ray.scale_exponent));
            }
        }
    }
    hits[i] = h;
}
