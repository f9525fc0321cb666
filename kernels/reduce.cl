/* Deterministic gradient reduction: splat g's gradient is the sum, in a fixed order (its tiles
 * row by row), of the per-tile shares the rasterize backward left in `contrib` [pairs, NQ].
 * pair_start [n + 1] (splat-id order) and pair_slot [pairs] come from binning. Every output
 * element is written (zeros for splats binned to no tile). NUM_CHANNELS is a build define. */
#include "common.h"

#define NQ GRAD_QUANTITIES(NUM_CHANNELS)

__kernel void reduce_grads(const int n, __global const int *pair_start,
                           __global const int *pair_slot, __global const float *contrib,
                           __global float *v_means2d, __global float *v_conics,
                           __global float *v_opac, __global float *v_feats)
{
    const int g = get_global_id(0);
    if (g >= n)
        return;
    float acc[NQ];
    for (int q = 0; q < NQ; ++q)
        acc[q] = 0.0f;
    for (int j = pair_start[g]; j < pair_start[g + 1]; ++j) {
        __global const float *c = contrib + (long)pair_slot[j] * NQ;
        for (int q = 0; q < NQ; ++q)
            acc[q] += c[q];
    }
    for (int q = 0; q < NQ; ++q)
        *grad_ptr(q, g, NUM_CHANNELS, v_means2d, v_conics, v_opac, v_feats) = acc[q];
}
