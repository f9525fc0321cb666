/* Per-pixel SSIM of two images with a separable Gaussian window (zero padding: taps outside the
 * image add nothing, as the training loss of 3DGS), forward and backward, one work-item per pixel.
 *
 * Images are [B, H, W, C] channel-last (the renderer's layout); NUM_CHANNELS (C) and WIN (the
 * window's odd width) are build defines, so one program per (channels, window) in use. gw[WIN] are
 * the normalised 1D weights. With x = a, y = b, per channel and pixel
 *   mx = G*x, my = G*y, exx = G*(x x), eyy = G*(y y), exy = G*(x y)
 *   S  = (2 mx my + C1)(2 (exy - mx my) + C2) / ((mx^2 + my^2 + C1)(exx - mx^2 + eyy - my^2 + C2))
 * and the output is S averaged over channels. The gradient flows to a only:
 *   dL/dx(p) = sum_q G(q - p) g(q) [dS/dmx(q) + 2 x(p) dS/dexx(q) + y(p) dS/dexy(q)] / C
 * (the window is symmetric, so the adjoint of the zero-padded blur is the same blur). The forward
 * leaves the three partials per channel in `part` for the backward; nothing else is stored.
 * Indices are 32-bit (the op checks 5 * C * pixels < 2^31): 64-bit address arithmetic per lane
 * cost 15-25% here. */
#include "common.h"

#define NQ_FWD 5 /* blurred statistics per channel */
#define NQ_BWD 3 /* partials per channel */

/* Intermediate buffers are planar, plane q of n pixels: consecutive work-items (the lanes a CPU
 * compiler vectorises across) then read and write consecutive addresses. */

/* The forward blurs columns first, on the two images, then rows, on the 5C statistics: the
 * vertical taps then read 2 images (a few cache lines per tap) and the horizontal taps of the 5C
 * planes overlap in cache; the other order read 5C planes vertically, 2x slower here. */

/* Vertical pass of the five statistics: vstat[q * C + c][b, y, x]. */
__kernel void ssim_fwd_v(const int n, const int height, const int width, __global const float *a,
                         __global const float *b, __constant float *gw, __global float *vstat)
{
    const int i = get_global_id(0); /* (view, y, x) flattened */
    if (i >= n)
        return;
    const int x = i % width, y = (i / width) % height;
    const int plane0 = i - y * width - x; /* pixel index of (view, 0, 0) */
    float s[NQ_FWD * NUM_CHANNELS];
    for (int q = 0; q < NQ_FWD * NUM_CHANNELS; ++q)
        s[q] = 0.0f;
    for (int t = 0; t < WIN; ++t) {
        /* Branch-free zero padding (the loops stay uniform across work-items, so they unroll and
         * vectorise): a tap outside the image reads the edge pixel and selects 0 instead (a select,
         * not a 0 weight, so a NaN/Inf edge pixel does not leak into the padding). */
        const int yr = y + t - WIN / 2, yy = clamp(yr, 0, height - 1);
        const int in = yr == yy;
        const float w = gw[t];
        const int o = (plane0 + yy * width + x) * NUM_CHANNELS;
        for (int c = 0; c < NUM_CHANNELS; ++c) {
            const float u = in ? a[o + c] : 0.0f, v = in ? b[o + c] : 0.0f;
            s[c] += w * u;
            s[NUM_CHANNELS + c] += w * v;
            s[2 * NUM_CHANNELS + c] += w * u * u;
            s[3 * NUM_CHANNELS + c] += w * v * v;
            s[4 * NUM_CHANNELS + c] += w * u * v;
        }
    }
    for (int q = 0; q < NQ_FWD * NUM_CHANNELS; ++q)
        vstat[q * n + i] = s[q];
}

/* Horizontal pass, SSIM and its partials: out[b, y, x] (channel mean), part[q * C + c][b, y, x]
 * = dS_c/d(mx, exx, exy) / C. */
__kernel void ssim_fwd_h(const int n, const int height, const int width, const float c1,
                         const float c2, __global const float *vstat, __constant float *gw,
                         __global float *out, __global float *part)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const int x = i % width;
    const int row = i - x; /* pixel index of (view, y, 0) */
    float s[NQ_FWD * NUM_CHANNELS];
    for (int q = 0; q < NQ_FWD * NUM_CHANNELS; ++q)
        s[q] = 0.0f;
    for (int t = 0; t < WIN; ++t) {
        const int xr = x + t - WIN / 2, xx = clamp(xr, 0, width - 1);
        const int in = xr == xx;
        const float w = gw[t];
        __global const float *h = vstat + row + xx;
        for (int q = 0; q < NQ_FWD * NUM_CHANNELS; ++q)
            s[q] += in ? w * h[q * n] : 0.0f;
    }
    float acc = 0.0f;
    const float inv_c = 1.0f / NUM_CHANNELS;
    for (int c = 0; c < NUM_CHANNELS; ++c) {
        const float mx = s[c], my = s[NUM_CHANNELS + c];
        const float exx = s[2 * NUM_CHANNELS + c], eyy = s[3 * NUM_CHANNELS + c];
        const float exy = s[4 * NUM_CHANNELS + c];
        const float A = 2.0f * mx * my + c1, Bn = 2.0f * (exy - mx * my) + c2;
        const float D = mx * mx + my * my + c1, E = (exx - mx * mx) + (eyy - my * my) + c2;
        const float S = (A * Bn) / (D * E);
        acc += S;
        /* dS/dmx = (2 my Bn - 2 my A) / (D E) - S (2 mx / D - 2 mx / E); dS/dexx = -S / E;
         * dS/dexy = 2 A / (D E). */
        const float DE = D * E;
        __global float *p = part + i;
        p[c * n] = ((2.0f * my * (Bn - A)) / DE - S * (2.0f * mx / D - 2.0f * mx / E)) * inv_c;
        p[(NUM_CHANNELS + c) * n] = -S / E * inv_c;
        p[(2 * NUM_CHANNELS + c) * n] = 2.0f * A / DE * inv_c;
    }
    out[i] = acc * inv_c;
}

/* Backward, horizontal pass of g(q) * partials(q): hgrad[q * C + c][b, y, x]. */
__kernel void ssim_bwd_h(const int n, const int height, const int width, __global const float *v_out,
                         __global const float *part, __constant float *gw, __global float *hgrad)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const int x = i % width;
    const int row = i - x;
    float s[NQ_BWD * NUM_CHANNELS];
    for (int q = 0; q < NQ_BWD * NUM_CHANNELS; ++q)
        s[q] = 0.0f;
    for (int t = 0; t < WIN; ++t) {
        const int xr = x + t - WIN / 2, xx = clamp(xr, 0, width - 1);
        const int in = xr == xx;
        const float w = gw[t] * v_out[row + xx];
        __global const float *p = part + row + xx;
        for (int q = 0; q < NQ_BWD * NUM_CHANNELS; ++q)
            s[q] += in ? w * p[q * n] : 0.0f;
    }
    for (int q = 0; q < NQ_BWD * NUM_CHANNELS; ++q)
        hgrad[q * n + i] = s[q];
}

/* Backward, vertical pass and the chain to the pixels of a: v_a[b, y, x, c]. */
__kernel void ssim_bwd_v(const int n, const int height, const int width, __global const float *a,
                         __global const float *b, __global const float *hgrad,
                         __constant float *gw, __global float *v_a)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const int x = i % width, y = (i / width) % height;
    const int plane0 = i - y * width - x;
    float s[NQ_BWD * NUM_CHANNELS];
    for (int q = 0; q < NQ_BWD * NUM_CHANNELS; ++q)
        s[q] = 0.0f;
    for (int t = 0; t < WIN; ++t) {
        const int yr = y + t - WIN / 2, yy = clamp(yr, 0, height - 1);
        const int in = yr == yy;
        const float w = gw[t];
        __global const float *h = hgrad + plane0 + yy * width + x;
        for (int q = 0; q < NQ_BWD * NUM_CHANNELS; ++q)
            s[q] += in ? w * h[q * n] : 0.0f;
    }
    const int o = i * NUM_CHANNELS;
    for (int c = 0; c < NUM_CHANNELS; ++c)
        v_a[o + c] = s[c] + 2.0f * a[o + c] * s[NUM_CHANNELS + c] + b[o + c] * s[2 * NUM_CHANNELS + c];
}
