/* Slabs: the points of a stage in buckets along one axis, so that FPS and the kNN look only
 * at the points near a point on that axis where that is exact (pgn_geom.c, pgn_knn.c,
 * pgn_knn_codes16.c). Built without fast-math, like them.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "pgn_geom.h"

/* Floats of the 16-bit indices (n + 32 of them), rounded up: what follows stays aligned. */
static inline int64_t idx16_floats(int64_t n) { return (n + 33) / 2; }

/* Scratch floats pgn_slab_build needs for n points: coordinates and indices (n + 16 each),
 * buckets (n + 257 + 15), 16-bit indices, FPS's block maxima and indices (n / 16 + 16 each)
 * and its distances (n + 16). */
int64_t pgn_slab_floats(int64_t n) {
    return 4 * (n + 16) + n + 257 + 15 + idx16_floats(n) + 2 * (n / 16 + 16) + (n + 16);
}

/* The points in 256 buckets along their widest axis: a point's slab, the points near it on
 * that axis, is then one run of them, whole buckets (pgn_slab_range). FPS updates only the
 * buckets near each new point (pgn_fps_in, AVX-512), and the kNN on 16-bit codes searches
 * them (pgn_knn_in, AVX-512 BW and VBMI2). Built where AVX-512 runs, n >= 6 k (stage 1 of the
 * default: 1,024 points, k 120) and n < 65,536 (16-bit indices); else, or for points with
 * no spread, it returns 0 (no slab) and both search all points. A counting sort: within a bucket,
 * index order. A pure function of the points: every thread's centres see the same slabs.
 * buf: pgn_slab_floats(n). */
int pgn_slab_build(const float *x, const float *y, const float *z, int64_t n, int64_t k,
                   float *buf, pgn_slab *sl) {
#if !defined(__AVX512F__)
    (void)x; (void)y; (void)z; (void)n; (void)k; (void)buf; (void)sl;
    return 0;
#else
    if (n < 6 * k || n >= 65536 || k < 1) return 0;
    const float *ax[3] = {x, y, z};
    float lo[3], w[3];
    for (int a = 0; a < 3; ++a) {  /* min and max: exact in any order */
        const float *v = ax[a];
        float fmn = v[0], fmx = v[0];
#pragma omp simd reduction(min:fmn) reduction(max:fmx)
        for (int64_t i = 0; i < n; ++i) {
            fmn = v[i] < fmn ? v[i] : fmn;
            fmx = v[i] > fmx ? v[i] : fmx;
        }
        lo[a] = fmn;
        w[a] = fmx - fmn;
    }
    const int a = w[0] >= w[1] && w[0] >= w[2] ? 0 : (w[1] >= w[2] ? 1 : 2);
    if (!(w[a] > 0.0f) || !isfinite(w[a])) return 0;
    float *sx = buf, *sy = sx + n + 16, *sz = sy + n + 16;
    int32_t *idx = (int32_t *)(sz + n + 16), *bk = idx + n + 16, *cnt = bk + n;
    const float *v = ax[a], sc = 255.0f / w[a];
    memset(cnt, 0, sizeof(int32_t) * 257);
    sl->lo = lo[a];
    sl->sc = sc;
    for (int64_t i = 0; i < n; ++i) {  /* monotone in v: buckets keep the values' order */
        const int32_t b = slab_bucket(sl, v[i]);
        bk[i] = b;
        cnt[b + 1]++;
    }
    for (int b = 0; b < 256; ++b) cnt[b + 1] += cnt[b];
    for (int64_t i = 0; i < n; ++i) idx[cnt[bk[i]]++] = (int32_t)i;  /* cnt[b]: bucket b's end */
    uint16_t *i16 = (uint16_t *)(cnt + 257 + 15);
    for (int64_t p = 0; p < n; ++p) {
        sx[p] = x[idx[p]]; sy[p] = y[idx[p]]; sz[p] = z[idx[p]];
        i16[p] = (uint16_t)idx[p];
    }
    for (int64_t p = n; p < n + 32; ++p) i16[p] = 0;
    for (int64_t p = n; p < n + 16; ++p) {   /* FPS's last block (pgn_fps_in): inert points */
        sx[p] = sy[p] = sz[p] = 0.0f;
        idx[p] = INT32_MAX;
    }
    sl->n = n;
    sl->axis = a;
    sl->s[0] = sx; sl->s[1] = sy; sl->s[2] = sz;
    sl->idx = idx;
    sl->idx16 = i16;
    sl->bend = cnt;
    sl->bmax = (float *)(cnt + 257 + 15) + idx16_floats(n);
    sl->barg = (int32_t *)(sl->bmax + n / 16 + 16);
    sl->fmd = (float *)(sl->barg + n / 16 + 16);
    return 1;
#endif
}
