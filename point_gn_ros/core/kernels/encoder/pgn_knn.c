/* Point-GN k nearest neighbours: each centre's k nearest points, ties to the lower index.
 * This file: the search on float distances (any CPU), the guess and the entry points;
 * pgn_knn_codes16.c: the search on 16-bit codes (AVX-512 BW and VBMI2); pgn_slab.c: the slabs.
 *
 * Built exact (no fast-math, no contraction: SOURCE_FLAGS), like pgn_geom.c: every distance
 * is rounded like the oracle's torch ops ((dx*dx + dy*dy) + dz*dz), so the choices are
 * the oracle's, ties included.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>
#if defined(__AVX512F__) || defined(__AVX2__)
#include <immintrin.h>
#endif

#include "pgn_knn.h"

static inline int64_t count_le(const float *d, int64_t n, float tau) {
    int64_t c = 0, i = 0;
#if defined(__AVX512F__)
    /* per-lane int32 counters bumped under the compare mask (no mask moved to a general
     * register per vector), two chains, summed once */
    const __m512 vt = _mm512_set1_ps(tau);
    const __m512i one = _mm512_set1_epi32(1);
    __m512i c0 = _mm512_setzero_si512(), c1 = c0;
    for (; i + 32 <= n; i += 32) {
        c0 = _mm512_mask_add_epi32(c0, _mm512_cmp_ps_mask(_mm512_loadu_ps(d + i), vt,
                                                          _CMP_LE_OQ), c0, one);
        c1 = _mm512_mask_add_epi32(c1, _mm512_cmp_ps_mask(_mm512_loadu_ps(d + i + 16), vt,
                                                          _CMP_LE_OQ), c1, one);
    }
    c = _mm512_reduce_add_epi32(_mm512_add_epi32(c0, c1));
#elif defined(__AVX2__)
    /* AVX2: per-lane int32 counters (a true compare is -1: subtract it), four chains,
     * summed once (movemask + popcount per vector was slower on Zen 3) */
    const __m256 vt = _mm256_set1_ps(tau);
    __m256i c0 = _mm256_setzero_si256(), c1 = c0, c2 = c0, c3 = c0;
    for (; i + 32 <= n; i += 32) {
        c0 = _mm256_sub_epi32(c0, _mm256_castps_si256(
            _mm256_cmp_ps(_mm256_loadu_ps(d + i), vt, _CMP_LE_OQ)));
        c1 = _mm256_sub_epi32(c1, _mm256_castps_si256(
            _mm256_cmp_ps(_mm256_loadu_ps(d + i + 8), vt, _CMP_LE_OQ)));
        c2 = _mm256_sub_epi32(c2, _mm256_castps_si256(
            _mm256_cmp_ps(_mm256_loadu_ps(d + i + 16), vt, _CMP_LE_OQ)));
        c3 = _mm256_sub_epi32(c3, _mm256_castps_si256(
            _mm256_cmp_ps(_mm256_loadu_ps(d + i + 24), vt, _CMP_LE_OQ)));
    }
    const __m256i cs = _mm256_add_epi32(_mm256_add_epi32(c0, c1), _mm256_add_epi32(c2, c3));
    __m128i h = _mm_add_epi32(_mm256_castsi256_si128(cs), _mm256_extracti128_si256(cs, 1));
    h = _mm_add_epi32(h, _mm_shuffle_epi32(h, 0x4e));
    h = _mm_add_epi32(h, _mm_shuffle_epi32(h, 0xb1));
    c = _mm_cvtsi128_si32(h);
#endif
    for (; i < n; ++i) c += d[i] <= tau;
    return c;
}

#if defined(__AVX2__) && !defined(__AVX512F__)
/* compress_lut[m]: the set lanes of the 8-bit mask m, in order, then zeros (one byte each) */
static uint8_t compress_lut[256][8];
__attribute__((constructor)) static void init_compress_lut(void) {  /* at library load */
    for (int m = 0; m < 256; ++m) {
        int c = 0;
        for (int l = 0; l < 8; ++l) if (m >> l & 1) compress_lut[m][c++] = (uint8_t)l;
        for (; c < 8; ++c) compress_lut[m][c] = 0;
    }
}
#endif

/* Indices i with d[i] <= lo into a (returns count); lo < d[i] <= hi into b (*nb). */
static int64_t split3(const float *d, int64_t n, float lo, float hi, int32_t *a, int32_t *b,
                      int64_t *nb) {
    int64_t ca = 0, cb = 0, i = 0;
#if defined(__AVX512F__)
    const __m512i step = _mm512_set1_epi32(16);
    __m512i idx = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const __m512 vlo = _mm512_set1_ps(lo), vhi = _mm512_set1_ps(hi);
    for (; i + 16 <= n; i += 16) {
        const __m512 v = _mm512_loadu_ps(d + i);
        const __mmask16 ma = _mm512_cmp_ps_mask(v, vlo, _CMP_LE_OQ);
        const __mmask16 mb = _mm512_cmp_ps_mask(v, vhi, _CMP_LE_OQ) & (__mmask16)~ma;
        /* compress into a register, then a plain store: compressing straight to
         * memory is microcoded and slow on AMD Zen 4 */
        _mm512_storeu_si512((void *)(a + ca), _mm512_maskz_compress_epi32(ma, idx));
        _mm512_storeu_si512((void *)(b + cb), _mm512_maskz_compress_epi32(mb, idx));
        ca += __builtin_popcount(ma);
        cb += __builtin_popcount(mb);
        idx = _mm512_add_epi32(idx, step);
    }
#elif defined(__AVX2__)
    /* AVX2 has no compress: a table of lane permutations for each 8-bit mask moves the
     * selected indices to the front, then one plain 8-lane store */
    const __m256i step = _mm256_set1_epi32(8);
    __m256i idx = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    const __m256 vlo = _mm256_set1_ps(lo), vhi = _mm256_set1_ps(hi);
    for (; i + 8 <= n; i += 8) {
        const __m256 v = _mm256_loadu_ps(d + i);
        const unsigned ma = (unsigned)_mm256_movemask_ps(_mm256_cmp_ps(v, vlo, _CMP_LE_OQ));
        const unsigned mb = (unsigned)_mm256_movemask_ps(_mm256_cmp_ps(v, vhi, _CMP_LE_OQ)) & ~ma;
        _mm256_storeu_si256((__m256i *)(a + ca), _mm256_permutevar8x32_epi32(
            idx, _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)compress_lut[ma]))));
        ca += __builtin_popcount(ma);
        /* the middle band (a few points, scattered: a branch on it mispredicts) */
        _mm256_storeu_si256((__m256i *)(b + cb), _mm256_permutevar8x32_epi32(
            idx, _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)compress_lut[mb]))));
        cb += __builtin_popcount(mb);
        idx = _mm256_add_epi32(idx, step);
    }
#endif
    for (; i < n; ++i) {
        a[ca] = (int32_t)i;
        b[cb] = (int32_t)i;
        const int in_a = d[i] <= lo;
        ca += in_a;
        cb += !in_a && d[i] <= hi;
    }
    *nb = cb;
    return ca;
}


/* pgn_knn's search on float distances (any CPU). */
static void knn_f32(const float *x, const float *y, const float *z, int64_t n, const float *cx,
                    const float *cy, const float *cz, int64_t s, int64_t k, int32_t *nb,
                    float *dist, uint64_t *keys, float guess) {
    int32_t *mid = (int32_t *)keys;          /* n + 16 int32 */
    uint64_t *mk = keys + (n + 16);          /* up to n keys */
    for (int64_t c = 0; c < s; ++c) {
        int32_t *row = nb + c * k;
        const float px = cx[c], py = cy[c], pz = cz[c];
        const float g1 = guess * 0.6f, g2 = guess * 1.6f;
        float dmax = 0.0f;
        int32_t c1 = 0, c2 = 0;
#pragma omp simd reduction(max:dmax) reduction(+:c1, c2)
        for (int64_t i = 0; i < n; ++i) {
            float dx = px - x[i], dy = py - y[i], dz = pz - z[i];
            float d = dx * dx;
            d = d + dy * dy;
            d = d + dz * dz;
            dist[i] = d;
            dmax = d > dmax ? d : dmax;
            c1 += d <= g1;
            c2 += d <= g2;
        }
        /* invariant: count(d <= lo) = clo < k <= chi = count(d <= hi) */
        float lo = -1.0f, hi = dmax;
        int64_t clo = 0, chi = n;
        if (c1 >= k) { hi = g1; chi = c1; }
        else if (c2 >= k) { lo = g1; clo = c1; hi = g2; chi = c2; }
        else { lo = g2; clo = c2; }
        for (int it = 0; it < 12 && chi - clo > 24; ++it) {
            const float tau = bracket_tau(lo, hi, clo, chi, k);
            if (!(tau > lo && tau < hi)) break;  /* bracket can no longer shrink (ties) */
            const int64_t ct = count_le(dist, n, tau);
            if (ct >= k) { hi = tau; chi = ct; } else { lo = tau; clo = ct; }
        }
        int64_t nm = 0;
        split3(dist, n, lo, hi, row, mid, &nm);
        for (int64_t j = 0; j < nm; ++j) mk[j] = make_key(dist[mid[j]], mid[j]);
        take_middle(mk, nm, k - clo, row + clo);
    }
}


/* A guess at the k-th smallest distance from a centre: 4 m2 k / n, m2 the points' mean
 * squared distance from their mean. Exact on a sphere's surface (a cap within chord r holds
 * r^2 / (4 rho^2) of it) and within a few times on object surfaces. 0 when not finite. */
float pgn_knn_guess(const float *x, const float *y, const float *z, int64_t n, int64_t k) {
    double mx = 0.0, my = 0.0, mz = 0.0, m2 = 0.0;
    for (int64_t i = 0; i < n; ++i) { mx += x[i]; my += y[i]; mz += z[i]; }
    mx /= (double)n; my /= (double)n; mz /= (double)n;
    for (int64_t i = 0; i < n; ++i)
        m2 += (x[i] - mx) * (x[i] - mx) + (y[i] - my) * (y[i] - my) + (z[i] - mz) * (z[i] - mz);
    const double g = 4.0 * m2 / (double)n * (double)k / (double)n;
    return g > 0.0 && g < 1e30 ? (float)g : 0.0f;
}



/* k nearest points (keys by distance then index) of each of s centres.
 * x, y, z: SoA points (n each); cx, cy, cz: centres (s each); nb: (s, k) int32 out,
 * unordered within a row, plus 16 int32 of writable slack after the last row.
 * dist: n floats scratch; keys: 2 n + 32 uint64 scratch; guess: pgn_knn_guess(x, y, z, n, k),
 * or 0 to compute it here; sl: these points' slab (pgn_slab_build), or NULL.
 *
 * The k-th smallest distance is bracketed by counting passes (interpolation): points at
 * or below the low end are in, and only the few between the ends are ordered by
 * (distance, index). The distance pass already counts at 0.6 and 1.6 times the guess,
 * which saves one or two counting passes; counts are exact, so a poor guess only costs
 * passes. A row's order follows its bracket (and its slab), so the guess depends on the
 * points alone: the rows are the same bits however the centres are split between calls
 * (threads). */
void pgn_knn_in(const float *x, const float *y, const float *z, int64_t n, const float *cx,
                const float *cy, const float *cz, int64_t s, int64_t k, int32_t *nb,
                float *dist, uint64_t *keys, float guess, const pgn_slab *sl) {
    if (k >= n) {
        for (int64_t c = 0; c < s; ++c)
            for (int64_t i = 0; i < n; ++i) nb[c * k + i] = (int32_t)i;
        return;
    }
    if (!(guess > 0.0f)) guess = pgn_knn_guess(x, y, z, n, k);
#if defined(__AVX512BW__) && defined(__AVX512VBMI2__)
    if (n >= 64 && n < 65536) {
        pgn_knn_codes(x, y, z, n, cx, cy, cz, s, k, nb, dist, keys, guess,
                      sl && sl->n == n ? sl : NULL);
        return;
    }
#endif
    (void)sl;  /* the float search scans every point: a slab does not pay for itself there */
    knn_f32(x, y, z, n, cx, cy, cz, s, k, nb, dist, keys, guess);
}

/* pgn_knn_in without a slab. */
void pgn_knn(const float *x, const float *y, const float *z, int64_t n, const float *cx,
             const float *cy, const float *cz, int64_t s, int64_t k, int32_t *nb, float *dist,
             uint64_t *keys, float guess) {
    pgn_knn_in(x, y, z, n, cx, cy, cz, s, k, nb, dist, keys, guess, NULL);
}
