/* Binning of splats to tiles without sorting pairs.
 *
 * The splats' rectangles are gathered in depth order. They are cut into contiguous chunks;
 * bin_count counts, per chunk, how many of its splats land in each tile; bin_scan_tiles and
 * bin_tile_ranges turn the counts into an exclusive scan over (tile, chunk), which gives every
 * chunk its own write position in every tile; bin_scatter writes the ids. Each tile's list is
 * therefore in depth order (chunk by chunk, each chunk in order) and the result is
 * deterministic: no atomics, no sort of the pairs. pair_slot lists, splat by splat, where its
 * pairs went, for the deterministic gradient reduction. Everything after bin_rects stays on the
 * device; the host only sums the areas and sorts the depths. */
#include "common.h"

/* Per splat (in id order, so every read is sequential): its tile rectangle, from the
 * opacity-aware extent capped by the radius, and that extent itself. Culled or invisible splats
 * get an empty rectangle and a negative extent. */
__kernel void bin_rects(const int n, __global const float *means2d, __global const float *conics,
                        __global const float *opac, __global const int *radii, const int tiles_x,
                        const int tiles_y, __global int4 *rects, __global float2 *ext,
                        __global int *area)
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
    area[g] = (r.z - r.x) * (r.w - r.y);
}

/* The visible splats' rectangles in depth order, so that the passes below read sequentially. */
__kernel void bin_gather(const int n_vis, __global const int4 *rects, __global const int *order,
                         __global int4 *sorted)
{
    const int s = get_global_id(0);
    if (s < n_vis)
        sorted[s] = rects[order[s]];
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

/* Per tile, the exclusive scan of its counts over the chunks, in place (hist becomes each
 * chunk's first slot within the tile), and the tile's total. Adjacent work-items read adjacent
 * tiles of a chunk's row. */
__kernel void bin_scan_tiles(const int n_tiles, const int n_chunks,
                             __global int *hist /* [chunks, n_tiles] */, __global int *tile_total)
{
    const int t = get_global_id(0);
    if (t >= n_tiles)
        return;
    int run = 0;
    for (int c = 0; c < n_chunks; ++c) {
        const long at = (long)c * n_tiles + t;
        const int v = hist[at];
        hist[at] = run;
        run += v;
    }
    tile_total[t] = run;
}

/* One work-item: each tile's [start, end) in ids from the totals (tile_end holds the totals on
 * entry). A few thousand additions: cheaper than a parallel scan's launches. */
__kernel void bin_tile_ranges(const int n_tiles, __global int *tile_start, __global int *tile_end)
{
    if (get_global_id(0) != 0)
        return;
    int s = 0;
    for (int t = 0; t < n_tiles; ++t) {
        tile_start[t] = s;
        s += tile_end[t];
        tile_end[t] = s;
    }
}

__kernel void bin_scatter(const int n_vis, const int chunk, const int n_tiles, const int tiles_x,
                          __global const int4 *rects, __global const int *order,
                          __global int *offsets /* [chunks, n_tiles], from bin_scan_tiles */,
                          __global const int *tile_start,
                          __global const int *pair_start /* [n + 1] by splat id */,
                          __global int *ids, __global int *pair_slot)
{
    const int c = get_global_id(0);
    const int s0 = c * chunk, s1 = min(n_vis, s0 + chunk);
    __global int *row = offsets + (long)c * n_tiles;
    for (int s = s0; s < s1; ++s) {
        int4 r = rects[s];
        int g = order[s];
        int j = pair_start[g]; /* splat g's pair slots, listed in its tiles' order */
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx) {
                const int t = ty * tiles_x + tx;
                const int slot = tile_start[t] + row[t]++;
                ids[slot] = g;
                pair_slot[j++] = slot;
            }
    }
}
