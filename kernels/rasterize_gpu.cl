/* Tile rasterizer for GPUs: one work-group per tile, one work-item per pixel.
 * Splats are staged through local memory in batches of one per work-item. The backward pass
 * reduces each splat's gradient over the tile in local memory (ROWS quantities at a time, in two
 * steps of fixed order: GROUP / ROWS partial sums of ROWS values, then their sum, so three
 * barriers per ROWS quantities rather than a tree's log2(GROUP) + 2) and then issues one atomic
 * add per quantity per splat per tile.
 *
 * GROUP (a build-time define, default 16x16 = one work-item per pixel of the tile) is the
 * work-group width. A device whose work-group or local-memory limit is below what 256 needs gets a
 * narrower GROUP (coin_cl/engine/limits.py chooses it): the work-group then walks its tile in
 * PASSES row bands of GROUP pixels, each band a complete pass over the tile's splats.
 *
 * With DETERMINISTIC the reduced values go to pair slots (see rasterize_cpu.cl) instead of atomics.
 * Same arguments, layouts and semantics as rasterize_cpu.cl (the tests hold both to the twin).
 * NUM_CHANNELS is a build-time define. OpenCL 1.2: barriers and local memory only. */
#include "common.h"

#define TILE_PIXELS (TILE_SIZE * TILE_SIZE)
#ifndef GROUP
#define GROUP TILE_PIXELS
#endif
#define PASSES (TILE_PIXELS / GROUP)
#if PASSES * GROUP != TILE_PIXELS || GROUP < TILE_SIZE
#error "GROUP must be a multiple of TILE_SIZE dividing TILE_SIZE * TILE_SIZE"
#endif
#define ROWS 8 /* quantities reduced per pass: local memory = ROWS * GROUP floats */
#define PARTS (GROUP / ROWS) /* partial sums per quantity, each of ROWS values */
#define NQ GRAD_QUANTITIES(NUM_CHANNELS)

inline void load_batch(int k0, int k1, __global const int *ids, __global const float *means2d,
                       __global const float *conics, __global const float *opac,
                       __local float4 *s_geo, __local float4 *s_con, __local int *s_id)
{
    const int lid = get_local_id(0);
    const int k = k0 + lid;
    if (k < k1) {
        const int g = ids[k];
        s_id[lid] = g;
        s_geo[lid] = (float4)(means2d[2 * g], means2d[2 * g + 1], opac[g], 0.0f);
        s_con[lid] = (float4)(conics[3 * g], conics[3 * g + 1], conics[3 * g + 2], 0.0f);
    }
}

__kernel __attribute__((reqd_work_group_size(GROUP, 1, 1)))
void rasterize_fwd(const int tiles_x, const int stride, const int plane,
                   __global const int *tile_start, __global const int *tile_end,
                   __global const int *ids, __global const float *means2d,
                   __global const float *conics, __global const float *opac,
                   __global const float2 *ext, /* unused: every pixel of the tile is evaluated */
                   __global const float *feats, __global const float *bg,
                   __global float *out_img, __global float *out_T, __global int *out_last)
{
    __local float4 s_geo[GROUP], s_con[GROUP];
    __local int s_id[GROUP];
    __local int s_done;
    const int tile = get_group_id(0), lid = get_local_id(0);
    const int start = tile_start[tile], end = tile_end[tile];
    for (int pass = 0; pass < PASSES; ++pass) {
        const int pix = pass * GROUP + lid;
        const int px = (tile % tiles_x) * TILE_SIZE + pix % TILE_SIZE;
        const int py = (tile / tiles_x) * TILE_SIZE + pix / TILE_SIZE;
        const float fx = (float)px + 0.5f, fy = (float)py + 0.5f;
        barrier(CLK_LOCAL_MEM_FENCE); /* the last pass is done reading s_done and the batch */
        float T = 1.0f, acc[NUM_CHANNELS];
        for (int ch = 0; ch < NUM_CHANNELS; ++ch)
            acc[ch] = 0.0f;
        int last = 0, done = 0;
        for (int k0 = start; k0 < end; k0 += GROUP) {
            const int k1 = min(end, k0 + GROUP);
            if (lid == 0)
                s_done = 0;
            barrier(CLK_LOCAL_MEM_FENCE);
            if (done)
                atomic_inc(&s_done);
            load_batch(k0, k1, ids, means2d, conics, opac, s_geo, s_con, s_id);
            barrier(CLK_LOCAL_MEM_FENCE);
            if (s_done == GROUP)
                break; /* uniform: every work-item read the same count after the barrier */
            for (int t = 0; t < k1 - k0 && !done; ++t) {
                const float4 geo = s_geo[t], con = s_con[t];
                const float dx = fx - geo.x, dy = fy - geo.y;
                const float sigma = 0.5f * (con.x * dx * dx + con.z * dy * dy) + con.y * dx * dy;
                const float alpha = fmin(MAX_ALPHA, geo.z * exp(-sigma));
                if (sigma < 0.0f || alpha < ALPHA_THRESHOLD)
                    continue;
                const float nT = T * (1.0f - alpha);
                if (nT <= TRANSMITTANCE_MIN) {
                    done = 1;
                    break;
                }
                const float w = alpha * T;
                const int g = s_id[t];
                for (int ch = 0; ch < NUM_CHANNELS; ++ch)
                    acc[ch] += w * feats[g * NUM_CHANNELS + ch];
                T = nT;
                last = k0 - start + t + 1;
            }
            barrier(CLK_LOCAL_MEM_FENCE); /* the batch is read before the next one overwrites it */
        }
        const int o = py * stride + px;
        for (int ch = 0; ch < NUM_CHANNELS; ++ch)
            out_img[ch * plane + o] = acc[ch] + T * bg[ch];
        out_T[o] = T;
        out_last[o] = last;
    }
}

__kernel __attribute__((reqd_work_group_size(GROUP, 1, 1)))
void rasterize_bwd(const int tiles_x, const int stride, const int plane,
                   __global const int *tile_start, __global const int *tile_end,
                   __global const int *ids, __global const float *means2d,
                   __global const float *conics, __global const float *opac,
                   __global const float2 *ext, /* unused: every pixel of the tile is evaluated */
                   __global const float *feats, __global const float *bg,
                   __global const float *out_T, __global const int *out_last,
                   __global const float *v_img, __global const float *v_alpha_img,
                   __global float *scratch, __global float *contrib,
                   __global float *v_means2d, __global float *v_conics,
                   __global float *v_opac, __global float *v_feats)
{
    __local float4 s_geo[GROUP], s_con[GROUP];
    __local int s_id[GROUP];
    __local float s_red[ROWS * GROUP];
    __local float s_part[ROWS * (PARTS + 1)]; /* padded: the final sums read it in strides */
    __local int s_max_last, s_any[2];
    const int tile = get_group_id(0), lid = get_local_id(0);
    const int start = tile_start[tile];
    float q[NQ]; /* this pixel's share of the current splat's gradients */
    for (int pass = 0; pass < PASSES; ++pass) {
        const int pix = pass * GROUP + lid;
        const int px = (tile % tiles_x) * TILE_SIZE + pix % TILE_SIZE;
        const int py = (tile / tiles_x) * TILE_SIZE + pix / TILE_SIZE;
        const float fx = (float)px + 0.5f, fy = (float)py + 0.5f;
        const int o = py * stride + px;
        float T = out_T[o];
        const int last = out_last[o];
        float gpix[NUM_CHANNELS], S[NUM_CHANNELS];
        float gb = v_alpha_img[o];
        for (int ch = 0; ch < NUM_CHANNELS; ++ch) {
            gpix[ch] = v_img[ch * plane + o];
            S[ch] = 0.0f;
            gb -= bg[ch] * gpix[ch];
        }
        const float bgterm = T * gb; /* d(T_final)/d(alpha_i) = -T_final / (1 - alpha_i) */
        /* The last pass is done with the flags, the batch and its contrib slots (which this pass
         * adds to from other work-items). */
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
        if (lid == 0) {
            s_max_last = 0;
            s_any[0] = s_any[1] = 0;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        atomic_max(&s_max_last, last);
        barrier(CLK_LOCAL_MEM_FENCE);
        const int kend = start + s_max_last;
#ifdef DETERMINISTIC
        /* every pair slot of the tile gets written in the first pass (later passes add to them);
         * those behind all last contributors get zeros */
        if (pass == 0)
            for (long i = (long)kend * NQ + lid; i < (long)tile_end[tile] * NQ; i += GROUP)
                contrib[i] = 0.0f;
#endif
        for (int k1 = kend; k1 > start; k1 -= GROUP) {
            const int k0 = max(start, k1 - GROUP);
            barrier(CLK_LOCAL_MEM_FENCE);
            load_batch(k0, k1, ids, means2d, conics, opac, s_geo, s_con, s_id);
            barrier(CLK_LOCAL_MEM_FENCE);
            for (int t = k1 - k0 - 1; t >= 0; --t) {
                const int k = k0 + t;
                const float4 geo = s_geo[t], con = s_con[t];
                const int g = s_id[t];
                const float dx = fx - geo.x, dy = fy - geo.y;
                const float sigma = 0.5f * (con.x * dx * dx + con.z * dy * dy) + con.y * dx * dy;
                const float G = exp(-sigma);
                const float araw = geo.z * G;
                const float alpha = fmin(MAX_ALPHA, araw);
                const int valid = (k - start < last) && sigma >= 0.0f && alpha >= ALPHA_THRESHOLD;
                for (int i = 0; i < NQ; ++i)
                    q[i] = 0.0f;
                if (valid) {
                    const float ra = 1.0f / fmax(1.0f - alpha, ONE_MINUS_ALPHA_MIN);
                    T *= ra;
                    const float w = alpha * T;
                    float va = bgterm * ra;
                    for (int ch = 0; ch < NUM_CHANNELS; ++ch) {
                        const float f = feats[g * NUM_CHANNELS + ch];
                        q[6 + ch] = w * gpix[ch];
                        va += (f * T - S[ch] * ra) * gpix[ch];
                        S[ch] += w * f;
                    }
                    if (araw > MAX_ALPHA)
                        va = 0.0f;
                    const float vs = -araw * va;
                    q[0] = -vs * (con.x * dx + con.y * dy);
                    q[1] = -vs * (con.y * dx + con.z * dy);
                    q[2] = 0.5f * vs * dx * dx;
                    q[3] = vs * dx * dy;
                    q[4] = 0.5f * vs * dy * dy;
                    q[5] = va * G;
                }
                /* Skip the reduction when no pixel of the tile saw this splat. Two flags, used in
                 * turn: one is cleared only after the barrier that follows every read of it. */
                const int p = k & 1;
                barrier(CLK_LOCAL_MEM_FENCE);
                if (lid == 0)
                    s_any[1 - p] = 0;
                if (valid)
                    atomic_or(&s_any[p], 1);
                barrier(CLK_LOCAL_MEM_FENCE);
                if (!s_any[p]) {
#ifdef DETERMINISTIC
                    if (pass == 0)
                        for (int q = lid; q < NQ; q += GROUP)
                            contrib[(long)k * NQ + q] = 0.0f;
#endif
                    continue;
                }
                for (int q0 = 0; q0 < NQ; q0 += ROWS) {
                    /* The previous round's final sums read s_part only: s_red is free to write. */
                    for (int r = 0; r < ROWS; ++r)
                        s_red[r * GROUP + lid] = q0 + r < NQ ? q[q0 + r] : 0.0f;
                    barrier(CLK_LOCAL_MEM_FENCE);
                    { /* work-item lid: part j of row r, the ROWS values j, j + PARTS, ... */
                        const int r = lid / PARTS, j = lid % PARTS;
                        float acc = 0.0f;
                        for (int m = 0; m < ROWS; ++m)
                            acc += s_red[r * GROUP + j + m * PARTS];
                        s_part[r * (PARTS + 1) + j] = acc;
                    }
                    barrier(CLK_LOCAL_MEM_FENCE);
                    if (lid < ROWS && q0 + lid < NQ) {
                        const int qi = q0 + lid;
                        float v = 0.0f;
                        for (int j = 0; j < PARTS; ++j)
                            v += s_part[lid * (PARTS + 1) + j];
#ifdef DETERMINISTIC
                        const long slot = (long)k * NQ + qi;
                        contrib[slot] = pass == 0 ? v : contrib[slot] + v;
#else
                        if (v != 0.0f)
                            atomic_add_float(grad_ptr(qi, g, NUM_CHANNELS, v_means2d, v_conics, v_opac, v_feats), v);
#endif
                    }
                }
            }
        }
    }
}
