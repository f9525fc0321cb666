/* Every constant of the renderer, mirrored in coin_cl/engine/constants.py (tests/test_constants.py
 * checks the two agree). Knobs guarded by #ifndef may be overridden with -D at build time, which
 * is how the benchmark trades error for speed; the defaults are the paper's (gsplat's) values. */
#ifndef COIN_COMMON_H
#define COIN_COMMON_H

#define TILE_SIZE 16
#define NEAR_PLANE 0.01f
#define FAR_PLANE 1e10f
#define EPS2D 0.3f
#ifndef ALPHA_THRESHOLD
#define ALPHA_THRESHOLD (1.0f / 255.0f)
#endif
#define MAX_ALPHA 0.99f
#ifndef TRANSMITTANCE_MIN
#define TRANSMITTANCE_MIN 1e-4f
#endif
#define ONE_MINUS_ALPHA_MIN 1e-6f
#define SIGMA_RADIUS 3.0f
#define FRUSTUM_MARGIN 0.3f
#define EIGEN_FLOOR 0.1f
#define MAX_RADIUS_PX 16777216

/* Half extents (pixels) of the box outside which o * exp(-sigma) < ALPHA_THRESHOLD, capped at the
 * 3-sigma radius and padded by one pixel for rounding. Binning and both rasterize passes use it,
 * so skipping pixels outside it never changes a result; it only saves work. Returns 0 when the
 * splat can never reach the threshold (invisible: opacity too low or not finite). */
inline int splat_extent(float3 conic, float opac, int radius, float *ext_x, float *ext_y)
{
    if (!(opac >= ALPHA_THRESHOLD) || !(opac <= 3.0e38f) || radius <= 0)
        return 0;
    float t = log(opac / ALPHA_THRESHOLD);
    float det = conic.x * conic.z - conic.y * conic.y;
    if (!(det > 0.0f))
        return 0;
    float cxx = conic.z / det, cyy = conic.x / det;
    *ext_x = fmin((float)radius, sqrt(2.0f * fmax(t, 0.0f) * cxx) + 1.0f);
    *ext_y = fmin((float)radius, sqrt(2.0f * fmax(t, 0.0f) * cyy) + 1.0f);
    return 1;
}

/* Half-open tile rectangle (x0, y0, x1, y1) of a box of half extents (ex, ey) around m. */
inline int4 tile_rect(float2 m, float ex, float ey, int tiles_x, int tiles_y)
{
    int4 r;
    r.x = clamp((int)floor((m.x - ex) / TILE_SIZE), 0, tiles_x);
    r.y = clamp((int)floor((m.y - ey) / TILE_SIZE), 0, tiles_y);
    r.z = clamp((int)ceil((m.x + ex) / TILE_SIZE), 0, tiles_x);
    r.w = clamp((int)ceil((m.y + ey) / TILE_SIZE), 0, tiles_y);
    if (r.z <= r.x || r.w <= r.y)
        r = (int4)(0, 0, 0, 0);
    return r;
}

/* Float add by compare-and-swap: OpenCL 1.2 has no float atomics. Exact under contention.
 * Every access to *addr is atomic (the first guess is 0, the buffers' initial value), so strict
 * race checkers such as Oclgrind see no plain read racing with the swaps. */
inline void atomic_add_float(volatile __global float *addr, float val)
{
#if defined(USE_FLOAT_ATOMICS)
    atomic_fetch_add_explicit((volatile __global atomic_float *)addr, val, memory_order_relaxed);
#else
    volatile __global unsigned int *p = (volatile __global unsigned int *)addr;
    unsigned int expected = 0u;
    for (;;) {
        unsigned int prev = atomic_cmpxchg(p, expected, as_uint(as_float(expected) + val));
        if (prev == expected)
            break;
        expected = prev;
    }
#endif
}

/* The per-splat gradient quantities a rasterize backward produces, in this order:
 * d means2d (2), d conics (3), d opacity (1), d features (NUM_CHANNELS). */
#define GRAD_QUANTITIES(nch) (6 + (nch))

/* Where quantity q of splat g's gradient lives in the per-splat gradient buffers. */
inline __global float *grad_ptr(int q, int g, int nch, __global float *v_means2d,
                                __global float *v_conics, __global float *v_opac,
                                __global float *v_feats)
{
    return q < 2 ? v_means2d + 2 * g + q
         : q < 5 ? v_conics + 3 * g + (q - 2)
         : q < 6 ? v_opac + g
                 : v_feats + g * nch + (q - 6);
}

#endif
