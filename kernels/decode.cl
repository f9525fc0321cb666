/* Scaffold-GS neural-Gaussian decode after its MLPs, forward and backward: from the MLP outputs of
 * the visible anchors (opacity, covariance, colour per offset) and the anchor parameters to the
 * activated Gaussians the rasterizer draws, so no per-offset temporaries are built in torch.
 *
 * Per drawn Gaussian m (offset j of visible anchor v, anchor a = vidx[v], s = v * k + j = sidx[m]):
 *   S       = exp(scaling[a])                       (6: offset scale, Gaussian scale)
 *   mean    = anchors[a] + offsets[a, j] * S[0:3]
 *   scale   = S[3:6] * sigmoid(cov[s, 0:3])
 *   quat    = cov[s, 3:7] / max(|cov[s, 3:7]|, 1e-12)
 *   opacity = opac[s], colour = col[s]               (already activated by the MLPs)
 * The backward runs one work-item per visible anchor over its k offsets, so the per-anchor sums
 * (the scaling gradient) need no atomics and every output element is written once. */
#include "common.h"

#define QUAT_NORM_MIN 1e-12f

inline float sigmoid1(float x) { return 1.0f / (1.0f + exp(-x)); }

__kernel void decode_fwd(const int n_drawn, const int k, __global const int *vidx,
                         __global const int *sidx, __global const float *anchors,
                         __global const float *offsets, __global const float *scaling,
                         __global const float *opac, __global const float *cov,
                         __global const float *col, __global float *means, __global float *quats,
                         __global float *scales, __global float *opac_out, __global float *col_out)
{
    const int m = get_global_id(0);
    if (m >= n_drawn)
        return;
    const int s = sidx[m], v = s / k, j = s - v * k, a = vidx[v];
    const long o = ((long)a * k + j) * 3;
    for (int c = 0; c < 3; ++c) {
        means[3 * m + c] = anchors[3 * a + c] + offsets[o + c] * exp(scaling[6 * a + c]);
        scales[3 * m + c] = exp(scaling[6 * a + 3 + c]) * sigmoid1(cov[7 * s + c]);
        col_out[3 * m + c] = col[3 * s + c];
    }
    const float r0 = cov[7 * s + 3], r1 = cov[7 * s + 4], r2 = cov[7 * s + 5], r3 = cov[7 * s + 6];
    const float n = fmax(sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3), QUAT_NORM_MIN);
    quats[4 * m] = r0 / n;
    quats[4 * m + 1] = r1 / n;
    quats[4 * m + 2] = r2 / n;
    quats[4 * m + 3] = r3 / n;
    opac_out[m] = opac[s];
}

/* midx[s]: the drawn index m of offset s, or -1 when the offset is not drawn (zero gradient).
 * v_offsets and v_scaling are written on the rows of visible anchors only (the caller zeroes the
 * rest: anchors outside the frustum get no gradient). */
__kernel void decode_bwd(const int n_vis, const int k, __global const int *vidx,
                         __global const int *midx, __global const float *offsets,
                         __global const float *scaling, __global const float *cov,
                         __global const float *v_means, __global const float *v_quats,
                         __global const float *v_scales, __global const float *v_opac_out,
                         __global const float *v_col_out, __global float *v_opac,
                         __global float *v_cov, __global float *v_col, __global float *v_offsets,
                         __global float *v_scaling)
{
    const int v = get_global_id(0);
    if (v >= n_vis)
        return;
    const int a = vidx[v];
    float S[6], gS[6];
    for (int c = 0; c < 6; ++c) {
        S[c] = exp(scaling[6 * a + c]);
        gS[c] = 0.0f;
    }
    for (int j = 0; j < k; ++j) {
        const int s = v * k + j, m = midx[s];
        const long o = ((long)a * k + j) * 3;
        if (m < 0) {
            v_opac[s] = 0.0f;
            for (int c = 0; c < 7; ++c)
                v_cov[7 * s + c] = 0.0f;
            for (int c = 0; c < 3; ++c) {
                v_col[3 * s + c] = 0.0f;
                v_offsets[o + c] = 0.0f;
            }
            continue;
        }
        v_opac[s] = v_opac_out[m];
        for (int c = 0; c < 3; ++c) {
            v_col[3 * s + c] = v_col_out[3 * m + c];
            const float gm = v_means[3 * m + c];
            v_offsets[o + c] = gm * S[c];
            gS[c] += gm * offsets[o + c];
            const float sg = sigmoid1(cov[7 * s + c]), gsc = v_scales[3 * m + c];
            v_cov[7 * s + c] = gsc * S[3 + c] * sg * (1.0f - sg);
            gS[3 + c] += gsc * sg;
        }
        float r[4], g[4];
        float nn = 0.0f;
        for (int i = 0; i < 4; ++i) {
            r[i] = cov[7 * s + 3 + i];
            g[i] = v_quats[4 * m + i];
            nn += r[i] * r[i];
        }
        const float n = sqrt(nn);
        if (n >= QUAT_NORM_MIN) { /* d(r/|r|) = (g - q (q . g)) / |r| */
            float qg = 0.0f;
            for (int i = 0; i < 4; ++i)
                qg += r[i] * g[i];
            qg /= n;
            for (int i = 0; i < 4; ++i)
                v_cov[7 * s + 3 + i] = (g[i] - r[i] / n * qg) / n;
        } else { /* the clamp holds the norm: r / 1e-12 is linear in r */
            for (int i = 0; i < 4; ++i)
                v_cov[7 * s + 3 + i] = g[i] / QUAT_NORM_MIN;
        }
    }
    for (int c = 0; c < 6; ++c)
        v_scaling[6 * a + c] = gS[c] * S[c]; /* d exp */
}
