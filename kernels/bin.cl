/* Binning of splats to tiles without sorting pairs.
 *
 * The splats' rectangles arrive in depth order. They are cut into contiguous chunks; pass 1
 * counts, per chunk, how many of its splats land in each tile; an exclusive scan over
 * (tile, chunk) gives every chunk its own write position in every tile; pass 2 writes the ids.
 * Each tile's list is therefore in depth order (chunk by chunk, each chunk in order) and the
 * result is deterministic: no atomics, no sort of the pairs. pair_slot lists, splat by splat,
 * where its pairs went, for the deterministic gradient reduction. */
#include "common.h"

/* Per splat (in id order, so every read is sequential): its tile rectangle, from the
 * opacity-aware extent capped by the radius, and that extent itself. Culled or invisible splats
 * get an empty rectangle and a negative extent. */
__kernel void bin_rects(const int n, __global const float *means2d, __global const float *conics,
                        __global const float *opac, __global const int *radii, const int tiles_x,
                        const int tiles_y, __global int4 *rects, __global float2 *ext)
{
    const int g = get_global_id(0);
    if (g >= n)
        return;
    float ex, ey;
    float3 con = (float3)(conics[3 * g], conics[3 * g + 1], conics[3 * g + 2]);
    int4 r = (int4)(0, 0, 0, 0);
    const int rad = radii[g];
    /* The box is not capped by the radius: inside a tile it is binned to, a splat is evaluated
     * on every pixel it can reach. Its tiles are those of the box capped by the radius. */
    if (rad > 0 && splat_extent(con, opac[g], MAX_RADIUS_PX, &ex, &ey))
        r = tile_rect((float2)(means2d[2 * g], means2d[2 * g + 1]), fmin(ex, (float)rad),
                      fmin(ey, (float)rad), tiles_x, tiles_y);
    else
        ex = ey = -1.0f;
    rects[g] = r;
    ext[g] = (float2)(ex, ey); /* the rasterizers' per-pixel box, computed once per splat */
}

__kernel void bin_count(const int n_vis, const int chunk, const int n_tiles, const int tiles_x,
                        __global const int4 *rects, __global int *hist /* [chunks, n_tiles] */)
{
    const int c = get_global_id(0);
    const int s0 = c * chunk, s1 = min(n_vis, s0 + chunk);
    __global int *h = hist + (long)c * n_tiles;
    for (int s = s0; s < s1; ++s) {
        int4 r = rects[s];
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx)
                h[ty * tiles_x + tx] += 1;
    }
}

__kernel void bin_scatter(const int n_vis, const int chunk, const int n_chunks, const int tiles_x,
                          __global const int4 *rects, __global const int *order,
                          __global int *offsets /* [n_tiles, chunks], exclusive scan */,
                          __global const int *pair_start /* [n + 1] by splat id */,
                          __global int *ids, __global int *pair_slot)
{
    const int c = get_global_id(0);
    const int s0 = c * chunk, s1 = min(n_vis, s0 + chunk);
    for (int s = s0; s < s1; ++s) {
        int4 r = rects[s];
        int g = order[s];
        int j = pair_start[g]; /* splat g's pair slots, listed in its tiles' order */
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx) {
                long at = (long)(ty * tiles_x + tx) * n_chunks + c;
                const int slot = offsets[at]++;
                ids[slot] = g;
                pair_slot[j++] = slot;
            }
    }
}
