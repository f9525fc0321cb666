/* Reprojection-based feature warping (CoIn paper 4.3): points P -> source view (bilinear feature
 * gather) -> target view (z-buffered splat). Forward and backward, OpenCL C 1.2, no atomics.
 *
 * cam = [R (9, row-major), t (3), fx, fy, cx, cy]: world-to-camera, OpenCV axes, pixel centres at
 * +0.5 (coin_cl.scene.conventions). Build defines: NUM_CHANNELS (feature count C), FOOTPRINT
 * (0 = the target pixel holding the projection, weight 1; 1 = bilinear: the 2x2 pixel centres
 * around it with bilinear weights).
 *
 * Determinism: every pass owns what it writes. Points are binned to 16x16 tiles without atomics
 * (per-chunk counts, a host scan, per-chunk writes: each tile's list comes out in point-id order),
 * then one work-item per tile walks its list in that order: the target tiles resolve the z-buffer
 * and sum the winners, the source tiles sum the feature gradients of the pixels they own. Sums
 * run in a fixed order, so both passes are bit-reproducible, and no float is ever added
 * concurrently (there is nothing for a race checker to find). */
#include "common.h"

#pragma OPENCL FP_CONTRACT OFF /* forward and backward must round the winner test identically */

#ifndef FOOTPRINT
#define FOOTPRINT 1
#endif
#if FOOTPRINT
#define FP_TAPS 4
#else
#define FP_TAPS 1
#endif

/* Point status codes (coin_cl/warp.py mirrors them); a point gets its first failure. */
#define WARP_OK 0
#define WARP_NONFINITE 1
#define WARP_BEHIND_SRC 2
#define WARP_OUTSIDE_SRC 3
#define WARP_OCCLUDED_SRC 4
#define WARP_BEHIND_DST 5
#define WARP_OUTSIDE_DST 6

/* Camera-space point and pixel position; returns 0 when z <= 0 or anything is not finite. */
inline int cam_project(__global const float *cam, float3 p, float *u, float *v, float *z)
{
    float x = cam[0] * p.x + cam[1] * p.y + cam[2] * p.z + cam[9];
    float y = cam[3] * p.x + cam[4] * p.y + cam[5] * p.z + cam[10];
    float w = cam[6] * p.x + cam[7] * p.y + cam[8] * p.z + cam[11];
    if (!(w > 0.0f) || !isfinite(w) || !isfinite(x) || !isfinite(y))
        return 0;
    *u = cam[12] * (x / w) + cam[14];
    *v = cam[13] * (y / w) + cam[15];
    *z = w;
    return isfinite(*u) && isfinite(*v);
}

/* Bilinear taps of a source position: corner pixels clamped to the image (edge replication),
 * weights (1-fx)(1-fy), fx(1-fy), (1-fx)fy, fx fy. */
inline void src_taps(float u, float v, int w, int h, int *px, int *py, float *wt)
{
    float x = u - 0.5f, y = v - 0.5f;
    float x0 = floor(x), y0 = floor(y);
    float fx = x - x0, fy = y - y0;
    int ix = (int)x0, iy = (int)y0;
    px[0] = clamp(ix, 0, w - 1); px[1] = clamp(ix + 1, 0, w - 1);
    py[0] = clamp(iy, 0, h - 1); py[1] = clamp(iy + 1, 0, h - 1);
    wt[0] = (1.0f - fx) * (1.0f - fy); wt[1] = fx * (1.0f - fy);
    wt[2] = (1.0f - fx) * fy;          wt[3] = fx * fy;
}

/* Target footprint of a projection (u, v): up to FP_TAPS pixels with weights; a tap outside the
 * image or of zero weight gets weight 0 (and is skipped by every pass). */
inline void dst_taps(float u, float v, int w, int h, int *px, int *py, float *wt)
{
#if FOOTPRINT
    float x = u - 0.5f, y = v - 0.5f;
    float x0 = floor(x), y0 = floor(y);
    float fx = x - x0, fy = y - y0;
    int ix = (int)x0, iy = (int)y0;
    float wx[2] = {1.0f - fx, fx}, wy[2] = {1.0f - fy, fy};
    for (int k = 0; k < 4; ++k) {
        int qx = ix + (k & 1), qy = iy + (k >> 1);
        px[k] = qx;
        py[k] = qy;
        wt[k] = (qx >= 0 && qx < w && qy >= 0 && qy < h) ? wx[k & 1] * wy[k >> 1] : 0.0f;
    }
#else
    px[0] = (int)floor(u);
    py[0] = (int)floor(v);
    wt[0] = (px[0] >= 0 && px[0] < w && py[0] >= 0 && py[0] < h) ? 1.0f : 0.0f;
#endif
}

/* The z-buffer rule: a candidate wins pixel p when its depth is within the relative tolerance of
 * the nearest candidate's. */
inline int wins(float z, float zmin, float tol)
{
    return z <= zmin * (1.0f + tol);
}

/* One work-item per point: validity, source taps, target projection and the tile rectangles of
 * both passes (empty for dropped points). */
__kernel void warp_points(const int m, __global const float *points, __global const float *src_cam,
                          __global const float *dst_cam, const int src_w, const int src_h,
                          const int dst_w, const int dst_h, __global const float *src_depth,
                          const int has_depth, const float src_depth_tol,
                          __global int *status, __global float2 *src_uv, __global float4 *dst_uvz,
                          __global int4 *src_rect, __global int4 *dst_rect)
{
    const int i = get_global_id(0);
    if (i >= m)
        return;
    float3 p = (float3)(points[3 * i], points[3 * i + 1], points[3 * i + 2]);
    float su = 0.0f, sv = 0.0f, sz = 0.0f, du = 0.0f, dv = 0.0f, dz = 0.0f;
    int st = WARP_OK;
    if (!(isfinite(p.x) && isfinite(p.y) && isfinite(p.z)))
        st = WARP_NONFINITE;
    else if (!cam_project(src_cam, p, &su, &sv, &sz))
        st = WARP_BEHIND_SRC;
    else if (!(su >= 0.0f && su < (float)src_w && sv >= 0.0f && sv < (float)src_h))
        st = WARP_OUTSIDE_SRC;
    else {
        if (has_depth) {
            /* nearest pixel: interpolating depth across a silhouette would invent surfaces */
            int qx = min((int)su, src_w - 1), qy = min((int)sv, src_h - 1);
            float d = src_depth[qy * src_w + qx];
            if (isfinite(d) && d > 0.0f && sz > d * (1.0f + src_depth_tol))
                st = WARP_OCCLUDED_SRC;
        }
        if (st == WARP_OK) {
            if (!cam_project(dst_cam, p, &du, &dv, &dz))
                st = WARP_BEHIND_DST;
            else if (!(du >= 0.0f && du < (float)dst_w && dv >= 0.0f && dv < (float)dst_h))
                st = WARP_OUTSIDE_DST;
        }
    }
    status[i] = st;
    src_uv[i] = (float2)(su, sv);
    dst_uvz[i] = (float4)(du, dv, dz, 0.0f);
    int4 rs = (int4)(0, 0, 0, 0), rd = (int4)(0, 0, 0, 0);
    if (st == WARP_OK) {
        int px[4], py[4];
        float wt[4];
        src_taps(su, sv, src_w, src_h, px, py, wt);
        rs = (int4)(px[0] / TILE_SIZE, py[0] / TILE_SIZE, px[1] / TILE_SIZE + 1, py[1] / TILE_SIZE + 1);
        dst_taps(du, dv, dst_w, dst_h, px, py, wt);
        int x0 = dst_w, y0 = dst_h, x1 = -1, y1 = -1;
        for (int k = 0; k < FP_TAPS; ++k)
            if (wt[k] > 0.0f) {
                x0 = min(x0, px[k]); x1 = max(x1, px[k]);
                y0 = min(y0, py[k]); y1 = max(y1, py[k]);
            }
        rd = (int4)(x0 / TILE_SIZE, y0 / TILE_SIZE, x1 / TILE_SIZE + 1, y1 / TILE_SIZE + 1);
    }
    src_rect[i] = rs;
    dst_rect[i] = rd;
}

/* Binning, pass 1: per chunk of consecutive points, how many land in each tile. */
__kernel void warp_bin_count(const int m, const int chunk, const int n_tiles, const int tiles_x,
                             __global const int4 *rects, __global int *hist /* [chunks, n_tiles] */)
{
    const int c = get_global_id(0);
    const int s0 = c * chunk, s1 = min(m, s0 + chunk);
    __global int *h = hist + (long)c * n_tiles;
    for (int s = s0; s < s1; ++s) {
        int4 r = rects[s];
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx)
                h[ty * tiles_x + tx] += 1;
    }
}

/* Binning, pass 2: each chunk writes its point ids at its own offsets (exclusive scan over
 * [tile, chunk]), so every tile list is in point-id order. */
__kernel void warp_bin_scatter(const int m, const int chunk, const int n_chunks, const int tiles_x,
                               __global const int4 *rects,
                               __global int *offsets /* [n_tiles, chunks] */, __global int *ids)
{
    const int c = get_global_id(0);
    const int s0 = c * chunk, s1 = min(m, s0 + chunk);
    for (int s = s0; s < s1; ++s) {
        int4 r = rects[s];
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx)
                ids[offsets[(long)(ty * tiles_x + tx) * n_chunks + c]++] = s;
    }
}

/* Forward, one work-item per target tile: z-buffer (min depth over the candidates of each
 * pixel), then the weighted mean of the winners' bilinearly gathered source features.
 * Outputs: feat [dst_h, dst_w, C], weight (sum of the winners' footprint weights, 0 = no
 * correspondence), depth (the z-buffer: nearest candidate's camera z, 0 where none). */
__kernel void warp_splat(const int tiles_x, const int dst_w, const int dst_h,
                         __global const int *tile_start, __global const int *tile_end,
                         __global const int *ids, __global const float2 *src_uv,
                         __global const float4 *dst_uvz, __global const float *src_feat,
                         const int src_w, const int src_h, const float depth_tol,
                         __global float *feat, __global float *weight, __global float *depth)
{
    const int t = get_global_id(0);
    const int x0 = (t % tiles_x) * TILE_SIZE, y0 = (t / tiles_x) * TILE_SIZE;
    const int x1 = min(dst_w, x0 + TILE_SIZE), y1 = min(dst_h, y0 + TILE_SIZE);
    if (y0 >= dst_h)
        return;
    for (int y = y0; y < y1; ++y)
        for (int x = x0; x < x1; ++x) {
            const long p = (long)y * dst_w + x;
            depth[p] = INFINITY;
            weight[p] = 0.0f;
            for (int c = 0; c < NUM_CHANNELS; ++c)
                feat[p * NUM_CHANNELS + c] = 0.0f;
        }
    const int j0 = tile_start[t], j1 = tile_end[t];
    int px[4], py[4];
    float wt[4];
    for (int j = j0; j < j1; ++j) {
        float4 d = dst_uvz[ids[j]];
        dst_taps(d.x, d.y, dst_w, dst_h, px, py, wt);
        for (int k = 0; k < FP_TAPS; ++k)
            if (wt[k] > 0.0f && px[k] >= x0 && px[k] < x1 && py[k] >= y0 && py[k] < y1) {
                const long p = (long)py[k] * dst_w + px[k];
                depth[p] = fmin(depth[p], d.z);
            }
    }
    float f[NUM_CHANNELS];
    for (int j = j0; j < j1; ++j) {
        const int i = ids[j];
        float4 d = dst_uvz[i];
        dst_taps(d.x, d.y, dst_w, dst_h, px, py, wt);
        int gathered = 0;
        for (int k = 0; k < FP_TAPS; ++k) {
            if (!(wt[k] > 0.0f && px[k] >= x0 && px[k] < x1 && py[k] >= y0 && py[k] < y1))
                continue;
            const long p = (long)py[k] * dst_w + px[k];
            if (!wins(d.z, depth[p], depth_tol))
                continue;
            if (!gathered) { /* only winners pay for the gather */
                int sx[2], sy[2];
                float b[4];
                float2 s = src_uv[i];
                src_taps(s.x, s.y, src_w, src_h, sx, sy, b);
                __global const float *f00 = src_feat + ((long)sy[0] * src_w + sx[0]) * NUM_CHANNELS;
                __global const float *f10 = src_feat + ((long)sy[0] * src_w + sx[1]) * NUM_CHANNELS;
                __global const float *f01 = src_feat + ((long)sy[1] * src_w + sx[0]) * NUM_CHANNELS;
                __global const float *f11 = src_feat + ((long)sy[1] * src_w + sx[1]) * NUM_CHANNELS;
                for (int c = 0; c < NUM_CHANNELS; ++c)
                    f[c] = b[0] * f00[c] + b[1] * f10[c] + b[2] * f01[c] + b[3] * f11[c];
                gathered = 1;
            }
            weight[p] += wt[k];
            __global float *o = feat + p * NUM_CHANNELS;
            for (int c = 0; c < NUM_CHANNELS; ++c)
                o[c] += wt[k] * f[c];
        }
    }
    for (int y = y0; y < y1; ++y)
        for (int x = x0; x < x1; ++x) {
            const long p = (long)y * dst_w + x;
            const float ws = weight[p];
            if (ws > 0.0f) {
                const float inv = 1.0f / ws;
                for (int c = 0; c < NUM_CHANNELS; ++c)
                    feat[p * NUM_CHANNELS + c] *= inv;
            } else {
                depth[p] = 0.0f;
            }
        }
}

/* Backward, one work-item per source tile: d src_feat of the pixels it owns. Point i's
 * cotangent g_i = sum over the pixels p it wins of (w_ip / weight_p) v_feat[p] (a gather of at
 * most FP_TAPS pixels, recomputed with the forward's exact arithmetic), then d src_feat[q] +=
 * b_iq g_i for its bilinear corners q inside the tile, points in id order. */
__kernel void warp_grad(const int tiles_x, const int src_w, const int src_h,
                        __global const int *tile_start, __global const int *tile_end,
                        __global const int *ids, __global const float2 *src_uv,
                        __global const float4 *dst_uvz, const int dst_w, const int dst_h,
                        __global const float *depth, __global const float *weight,
                        __global const float *v_feat, const float depth_tol,
                        __global float *v_src)
{
    const int t = get_global_id(0);
    const int x0 = (t % tiles_x) * TILE_SIZE, y0 = (t / tiles_x) * TILE_SIZE;
    const int x1 = min(src_w, x0 + TILE_SIZE), y1 = min(src_h, y0 + TILE_SIZE);
    if (y0 >= src_h)
        return;
    for (int y = y0; y < y1; ++y)
        for (int x = x0; x < x1; ++x)
            for (int c = 0; c < NUM_CHANNELS; ++c)
                v_src[((long)y * src_w + x) * NUM_CHANNELS + c] = 0.0f;
    float g[NUM_CHANNELS];
    int px[4], py[4];
    float wt[4];
    for (int j = tile_start[t]; j < tile_end[t]; ++j) {
        const int i = ids[j];
        float4 d = dst_uvz[i];
        dst_taps(d.x, d.y, dst_w, dst_h, px, py, wt);
        for (int c = 0; c < NUM_CHANNELS; ++c)
            g[c] = 0.0f;
        int any = 0;
        for (int k = 0; k < FP_TAPS; ++k) {
            if (!(wt[k] > 0.0f))
                continue;
            const long p = (long)py[k] * dst_w + px[k];
            if (!wins(d.z, depth[p], depth_tol))
                continue;
            const float a = wt[k] / weight[p];
            __global const float *vp = v_feat + p * NUM_CHANNELS;
            for (int c = 0; c < NUM_CHANNELS; ++c)
                g[c] += a * vp[c];
            any = 1;
        }
        if (!any)
            continue;
        int sx[2], sy[2];
        float b[4];
        float2 s = src_uv[i];
        src_taps(s.x, s.y, src_w, src_h, sx, sy, b);
        for (int k = 0; k < 4; ++k) {
            const int qx = sx[k & 1], qy = sy[k >> 1];
            if (qx < x0 || qx >= x1 || qy < y0 || qy >= y1)
                continue;
            __global float *o = v_src + ((long)qy * src_w + qx) * NUM_CHANNELS;
            for (int c = 0; c < NUM_CHANNELS; ++c)
                o[c] += b[k] * g[c];
        }
    }
}
