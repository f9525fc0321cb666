/* Tile rasterizer for CPUs: one work-group of one work-item per 16x16 tile; the work-item walks
 * the tile's depth-ordered splat list and vectorises over pixels, a tile row being two float8.
 * Only the rows and 8-pixel chunks inside a splat's opacity-aware box are evaluated. Reductions
 * of per-splat gradients happen in registers over the whole tile, then one compare-and-swap add
 * per splat per tile.
 *
 * Layouts: images are channel-major and padded to whole tiles, img[c][y][x] with row stride
 * `stride` (= tiles_x * 16) and channel plane `plane` (= stride * tiles_y * 16).
 * NUM_CHANNELS (the feature count) is a build-time define: one program per count in use. */
#include "common.h"

#define NCHUNK (TILE_SIZE / 8)
#define NVEC (TILE_SIZE * NCHUNK)

#ifdef ACC_DOUBLE
typedef double8 acc8;
#define ACC(x) convert_double8(x)
#define ACC_SUM(v) ((float)((v).s0 + (v).s1 + (v).s2 + (v).s3 + (v).s4 + (v).s5 + (v).s6 + (v).s7))
#else
typedef float8 acc8;
#define ACC(x) (x)
#define ACC_SUM(v) (((v).s0 + (v).s4) + ((v).s1 + (v).s5) + ((v).s2 + (v).s6) + ((v).s3 + (v).s7))
#endif

/* exp for x <= 0 with operators only (no built-in call): e^x = 2^n e^f with n = round(x / ln 2)
 * by the 1.5 * 2^23 trick, f = x - n ln 2 in two parts (Cody-Waite, so the reduction is exact
 * enough), e^f (|f| <= 0.35) by its degree-7 Taylor polynomial. Relative error ~1e-7, as the
 * built-in; below 2^-126 it returns 2^-126 (alpha is then far under ALPHA_THRESHOLD). */
inline float8 exp_neg8(float8 x)
{
    x = x < -87.0f ? (float8)(-87.0f) : x;
    const float8 magic = (float8)(12582912.0f);
    const float8 tm = x * 1.44269504f + magic;
    const float8 n = tm - magic;
    const float8 f = (x - n * 0.693145751953125f) - n * 1.428606820309417e-06f;
    const float8 p = 1.0f + f * (1.0f + f * (0.5f + f * (0.166666667f + f * (0.0416666667f +
                     f * (0.00833333333f + f * (0.00138888889f + f * 0.000198412698f))))));
    const int8 e = (as_int8(tm) - as_int8(magic) + 127) << 23;
    return p * as_float8(e);
}

#ifndef EXPF
#define EXPF exp_neg8
#endif

/* PoCL does not inline built-ins such as vload8, select, any or fmin: each becomes a call that
 * spills the vector registers. The hot loops use plain vector operators instead (aligned float8
 * accesses are safe: rows start at multiples of 8 floats of 32-byte aligned buffers). */
#define VLD(p) (*(__global const float8 *)(p))
#define VST(p, v) (*(__global float8 *)(p) = (v))
#define SEL(a, b, m) ((m) ? (b) : (a))
#define ANY(m) ((((m).s0 | (m).s1 | (m).s2 | (m).s3) | ((m).s4 | (m).s5 | (m).s6 | (m).s7)) != 0)
#define VMIN(x, y) ((x) < (y) ? (x) : (y))
#define VMAXF(x, c) ((x) > (c) ? (x) : (float8)(c))

/* A tile's share of splat g's gradient (quantity q, pair slot k): with DETERMINISTIC, stored in
 * slot k of `contrib` and summed per splat in a fixed order by reduce.cl (every slot is written,
 * zeros included); otherwise added straight into the gradients, one atomic per quantity. */
#define NQ GRAD_QUANTITIES(NUM_CHANNELS)
#ifdef DETERMINISTIC
#define EMIT(k, g, q, val) (contrib[(long)(k) * NQ + (q)] = (val))
#define ZERO_SLOT(k) for (int q_ = 0; q_ < NQ; ++q_) contrib[(long)(k) * NQ + q_] = 0.0f
#else
#define EMIT(k, g, q, val) \
    atomic_add_float(grad_ptr(q, g, NUM_CHANNELS, v_means2d, v_conics, v_opac, v_feats), (val))
#define ZERO_SLOT(k) ((void)0)
#endif

#define LANES ((float8)(0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f))

/* Rows [*r0, *r1] and chunks [*c0, *c1] of the tile inside the splat's box; 0 if none. */
inline int box_in_tile(float mx, float my, float ex, float ey, int px0, int py0,
                       int *r0, int *r1, int *c0, int *c1)
{
    *r0 = max(0, (int)ceil(my - ey - 0.5f - (float)py0));
    *r1 = min(TILE_SIZE - 1, (int)floor(my + ey - 0.5f - (float)py0));
    *c0 = max(0, (int)floor((mx - ex - 0.5f - (float)px0) / 8.0f));
    *c1 = min(NCHUNK - 1, (int)floor((mx + ex - 0.5f - (float)px0) / 8.0f));
    return *r0 <= *r1 && *c0 <= *c1;
}

typedef struct {
    float mx, my, A, B, C, o; /* mean, conic, opacity */
    int r0, r1, c0, c1;       /* rows and 8-pixel chunks of the tile inside its box */
} Splat;

/* Reads splat g; 0 if it cannot reach ALPHA_THRESHOLD anywhere in this tile. */
inline int load_splat(int g, __global const float *means2d, __global const float *conics,
                      __global const float *opac, __global const float2 *ext, int px0, int py0,
                      Splat *s)
{
    const float2 e = ext[g];
    s->mx = means2d[2 * g];
    s->my = means2d[2 * g + 1];
    s->A = conics[3 * g];
    s->B = conics[3 * g + 1];
    s->C = conics[3 * g + 2];
    s->o = opac[g];
    return e.x >= 0.0f && box_in_tile(s->mx, s->my, e.x, e.y, px0, py0, &s->r0, &s->r1, &s->c0, &s->c1);
}

__kernel void rasterize_fwd(const int tiles_x, const int stride, const int plane,
                            __global const int *tile_start, __global const int *tile_end,
                            __global const int *ids, __global const float *means2d,
                            __global const float *conics, __global const float *opac,
                            __global const float2 *ext,
                            __global const float *feats, __global const float *bg,
                            __global float *out_img, __global float *out_T, __global int *out_last)
{
    const int tile = get_global_id(0);
    const int px0 = (tile % tiles_x) * TILE_SIZE, py0 = (tile / tiles_x) * TILE_SIZE;
    const int base = py0 * stride + px0;
    float8 T[NVEC];
    int8 last[NVEC], done[NVEC];
    for (int v = 0; v < NVEC; ++v) {
        T[v] = (float8)(1.0f);
        last[v] = (int8)(0);
        done[v] = (int8)(0);
        int o = base + (v / NCHUNK) * stride + (v % NCHUNK) * 8;
        for (int ch = 0; ch < NUM_CHANNELS; ++ch)
            VST(out_img + ch * plane + o, (float8)(0.0f));
    }
    const int start = tile_start[tile], end = tile_end[tile];
    int n_done = 0;
    for (int k = start; k < end && n_done < TILE_SIZE * TILE_SIZE; ++k) {
        const int g = ids[k];
        Splat sp;
        if (!load_splat(g, means2d, conics, opac, ext, px0, py0, &sp))
            continue;
        const float mx = sp.mx, my = sp.my, A = sp.A, B = sp.B, C = sp.C, o = sp.o;
        const int r0 = sp.r0, r1 = sp.r1, c0 = sp.c0, c1 = sp.c1;
        const int8 idx8 = (int8)(k - start + 1);
        for (int r = r0; r <= r1; ++r) {
            const float dy = (float)(py0 + r) + 0.5f - my;
            const float hc = 0.5f * C * dy * dy, bdy = B * dy;
            for (int c = c0; c <= c1; ++c) {
                const int v = r * NCHUNK + c;
                const float8 dx = LANES + (float)(px0 + 8 * c) - mx;
                const float8 sigma = 0.5f * A * dx * dx + bdy * dx + hc;
                const float8 alpha = VMIN((float8)(MAX_ALPHA), o * EXPF(-sigma));
                const int8 valid = (sigma >= 0.0f) & (alpha >= ALPHA_THRESHOLD) & ~done[v];
                if (!ANY(valid))
                    continue;
                const float8 nT = T[v] * (1.0f - alpha);
                const int8 stop = valid & (nT <= TRANSMITTANCE_MIN);
                const int8 use = valid & ~stop;
                const float8 w = SEL((float8)(0.0f), alpha * T[v], use);
                __global float *dst = out_img + base + r * stride + 8 * c;
                for (int ch = 0; ch < NUM_CHANNELS; ++ch) {
                    float8 acc = VLD(dst + ch * plane);
                    VST(dst + ch * plane, acc + w * feats[g * NUM_CHANNELS + ch]);
                }
                T[v] = SEL(T[v], nT, use);
                last[v] = SEL(last[v], idx8, use);
                if (ANY(stop)) {
                    done[v] |= stop;
                    int8 cnt = -stop;
                    n_done += cnt.s0 + cnt.s1 + cnt.s2 + cnt.s3 + cnt.s4 + cnt.s5 + cnt.s6 + cnt.s7;
                }
            }
        }
    }
    for (int v = 0; v < NVEC; ++v) {
        int o = base + (v / NCHUNK) * stride + (v % NCHUNK) * 8;
        for (int ch = 0; ch < NUM_CHANNELS; ++ch) {
            float8 acc = VLD(out_img + ch * plane + o);
            VST(out_img + ch * plane + o, acc + T[v] * bg[ch]);
        }
        VST(out_T + o, T[v]);
        *(__global int8 *)(out_last + o) = last[v];
    }
}

__kernel void rasterize_bwd(const int tiles_x, const int stride, const int plane,
                            __global const int *tile_start, __global const int *tile_end,
                            __global const int *ids, __global const float *means2d,
                            __global const float *conics, __global const float *opac,
                            __global const float2 *ext,
                            __global const float *feats, __global const float *bg,
                            __global const float *out_T, __global const int *out_last,
                            __global const float *v_img, __global const float *v_alpha_img,
                            __global float *scratch, __global float *contrib,
                            __global float *v_means2d, __global float *v_conics,
                            __global float *v_opac, __global float *v_feats)
{
    const int tile = get_global_id(0);
    const int px0 = (tile % tiles_x) * TILE_SIZE, py0 = (tile / tiles_x) * TILE_SIZE;
    const int base = py0 * stride + px0;
    float8 T[NVEC], bgterm[NVEC];
    int8 last[NVEC];
    int max_last = 0;
    for (int v = 0; v < NVEC; ++v) {
        int o = base + (v / NCHUNK) * stride + (v % NCHUNK) * 8;
        T[v] = VLD(out_T + o);
        last[v] = *(__global const int8 *)(out_last + o);
        /* d(T_final)/d(alpha_i) = -T_final / (1 - alpha_i): the background and alpha outputs. */
        float8 gb = VLD(v_alpha_img + o);
        for (int ch = 0; ch < NUM_CHANNELS; ++ch) {
            gb -= bg[ch] * VLD(v_img + ch * plane + o);
            VST(scratch + ch * plane + o, (float8)(0.0f));
        }
        bgterm[v] = T[v] * gb;
        int8 l = last[v];
        max_last = max(max_last, max(max(max(l.s0, l.s1), max(l.s2, l.s3)), max(max(l.s4, l.s5), max(l.s6, l.s7))));
    }
    const int start = tile_start[tile], end = tile_end[tile];
    for (int k = start + max_last; k < end; ++k)
        ZERO_SLOT(k); /* behind every pixel's last contributor: no gradient */
    for (int k = start + max_last - 1; k >= start; --k) {
        const int g = ids[k];
        Splat sp;
        if (!load_splat(g, means2d, conics, opac, ext, px0, py0, &sp)) {
            ZERO_SLOT(k);
            continue;
        }
        const float mx = sp.mx, my = sp.my, A = sp.A, B = sp.B, C = sp.C, o = sp.o;
        const int r0 = sp.r0, r1 = sp.r1, c0 = sp.c0, c1 = sp.c1;
        const int8 kk = (int8)(k - start);
        float f[NUM_CHANNELS];
        acc8 vf[NUM_CHANNELS];
        for (int ch = 0; ch < NUM_CHANNELS; ++ch) {
            f[ch] = feats[g * NUM_CHANNELS + ch];
            vf[ch] = (acc8)(0);
        }
        acc8 vA = (acc8)(0), vB = (acc8)(0), vC = (acc8)(0);
        acc8 vmx = (acc8)(0), vmy = (acc8)(0), vo = (acc8)(0);
        int touched = 0;
        for (int r = r0; r <= r1; ++r) {
            const float dy = (float)(py0 + r) + 0.5f - my;
            const float hc = 0.5f * C * dy * dy, bdy = B * dy;
            for (int c = c0; c <= c1; ++c) {
                const int v = r * NCHUNK + c;
                const float8 dx = LANES + (float)(px0 + 8 * c) - mx;
                const float8 sigma = 0.5f * A * dx * dx + bdy * dx + hc;
                const float8 G = EXPF(-sigma);
                const float8 araw = o * G;
                const float8 alpha = VMIN((float8)(MAX_ALPHA), araw);
                const int8 valid = (kk < last[v]) & (sigma >= 0.0f) & (alpha >= ALPHA_THRESHOLD);
                if (!ANY(valid))
                    continue;
                touched = 1;
                const float8 ra = 1.0f / VMAXF(1.0f - alpha, ONE_MINUS_ALPHA_MIN);
                const float8 Ti = SEL(T[v], T[v] * ra, valid);
                T[v] = Ti;
                const float8 w = SEL((float8)(0.0f), alpha * Ti, valid);
                const int o8 = base + r * stride + 8 * c;
                float8 va = bgterm[v] * ra;
                for (int ch = 0; ch < NUM_CHANNELS; ++ch) {
                    const float8 gch = VLD(v_img + ch * plane + o8);
                    float8 S = VLD(scratch + ch * plane + o8);
                    vf[ch] += ACC(w * gch);
                    va += (f[ch] * Ti - S * ra) * gch;
                    VST(scratch + ch * plane + o8, S + w * f[ch]);
                }
                va = SEL((float8)(0.0f), va, valid & (araw <= MAX_ALPHA));
                vo += ACC(va * G);
                const float8 vs = -araw * va; /* dL/dsigma */
                vA += ACC(0.5f * vs * dx * dx);
                vB += ACC(vs * dx * dy);
                vC += ACC(0.5f * vs * dy * dy);
                vmx -= ACC(vs * (A * dx + bdy));
                vmy -= ACC(vs * (B * dx + C * dy));
            }
        }
        if (!touched) {
            ZERO_SLOT(k);
            continue;
        }
        EMIT(k, g, 0, ACC_SUM(vmx));
        EMIT(k, g, 1, ACC_SUM(vmy));
        EMIT(k, g, 2, ACC_SUM(vA));
        EMIT(k, g, 3, ACC_SUM(vB));
        EMIT(k, g, 4, ACC_SUM(vC));
        EMIT(k, g, 5, ACC_SUM(vo));
        for (int ch = 0; ch < NUM_CHANNELS; ++ch)
            EMIT(k, g, 6 + ch, ACC_SUM(vf[ch]));
    }
}
