/* Point-GN k nearest neighbours on 16-bit codes of the distances (AVX-512 BW and VBMI2; see
 * pgn_knn.c): 32 points a vector, in a centre's slab (pgn_slab.c) where that is exact.
 * Elsewhere pgn_knn.c searches on floats.
 *
 * Built exact (no fast-math, no contraction: SOURCE_FLAGS), like pgn_knn.c.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>
#if defined(__AVX512F__) || defined(__AVX2__)
#include <immintrin.h>
#endif

#include "pgn_knn.h"

#if defined(__AVX512BW__) && defined(__AVX512VBMI2__)
/* A distance's code: the top 16 bits of its float (d >= +0, so codes order like the
 * distances, ties and all), and the largest float with a given code. d <= code_top(q)
 * exactly when code(d) <= q. */
static inline int32_t code_of(float f) {
    uint32_t b;
    memcpy(&b, &f, 4);
    return (int32_t)(b >> 16);
}
static inline float code_top(int32_t q) {
    const uint32_t b = ((uint32_t)q << 16) | 0xFFFFu;
    float f;
    memcpy(&f, &b, 4);
    return f;
}

/* One centre's search with the counting and the split on 16-bit codes (AVX-512 BW and VBMI2,
 * 64 <= n < 65536): 32 points a vector instead of 16, and the split compresses 16-bit
 * indices. Brackets are whole codes, so every count is exact; a code spans 1/128 of a
 * distance, so its middle stays small, and the middle is ordered by the float keys.
 * x, y, z: n points; map: their indices in the row (NULL: 0..n-1), 32 readable past n.
 * h, a16, b16 and mk: the
 * scratch of pgn_knn_codes. slab: the points are a slab of the stage's (pgn_slab.c): only a
 * centre with at least k of them within the guess's outer count (1.6 guess) is searched
 * there (returns 1 and writes the row); else it returns 0 and writes nothing. */
static int codes_centre(const float *x, const float *y, const float *z, int64_t n,
                        const uint16_t *map, float qx, float qy, float qz, int64_t k,
                        int32_t *row, float *dist, uint16_t *h, uint16_t *a16, uint16_t *b16,
                        uint64_t *mk, float guess, int slab) {
    const int64_t nv = (n + 31) / 32;
    const __m512i one = _mm512_set1_epi32(1), step = _mm512_set1_epi16(32);
    static const uint16_t lanes[32] = {0,  1,  2,  3,  4,  5,  6,  7,  8,  9,  10,
                                       11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21,
                                       22, 23, 24, 25, 26, 27, 28, 29, 30, 31};
    const __m512i iota = _mm512_loadu_si512((const void *)lanes);
    const int32_t q1 = code_of(guess * 0.6f), q2 = code_of(guess * 1.6f);
    const float f1 = code_top(q1), f2 = code_top(q2);
    const __m512 px = _mm512_set1_ps(qx), py = _mm512_set1_ps(qy);
    const __m512 pz = _mm512_set1_ps(qz), g1 = _mm512_set1_ps(f1);
    const __m512 g2 = _mm512_set1_ps(f2);
    __m512i n1 = _mm512_setzero_si512(), n2 = n1;
    __m512 vmax = _mm512_setzero_ps();
    int64_t i = 0;
    for (; i + 16 <= n; i += 16) {  /* the oracle's rounding (a difference's sign is exact) */
        const __m512 d = sqdist16(x, y, z, i, px, py, pz);
        _mm512_storeu_ps(dist + i, d);
        _mm256_storeu_si256((__m256i *)(h + i), _mm512_cvtepi32_epi16(
            _mm512_srli_epi32(_mm512_castps_si512(d), 16)));
        vmax = _mm512_max_ps(vmax, d);
        n1 = _mm512_mask_add_epi32(n1, _mm512_cmp_ps_mask(d, g1, _CMP_LE_OQ), n1, one);
        n2 = _mm512_mask_add_epi32(n2, _mm512_cmp_ps_mask(d, g2, _CMP_LE_OQ), n2, one);
    }
    int64_t c1 = _mm512_reduce_add_epi32(n1), c2 = _mm512_reduce_add_epi32(n2);
    float dmax = _mm512_reduce_max_ps(vmax);
    for (; i < n; ++i) {
        const float dx = qx - x[i], dy = qy - y[i], dz = qz - z[i];
        float d = dx * dx;
        d = d + dy * dy;
        d = d + dz * dz;
        dist[i] = d;
        h[i] = (uint16_t)code_of(d);
        dmax = d > dmax ? d : dmax;
        c1 += d <= f1;
        c2 += d <= f2;
    }
    if (slab && c2 < k) return 0;
    for (; i < 32 * nv; ++i) h[i] = 0xFFFFu;  /* past n: above any distance */
    /* invariant over codes: count(code <= lo) = clo < k <= chi = count(code <= hi);
     * lo = -1: none */
    int32_t lo = -1, hi = code_of(dmax);
    int64_t clo = 0, chi = n;
    if (c1 >= k) { hi = q1; chi = c1; }
    else if (c2 >= k) { lo = q1; clo = c1; hi = q2; chi = c2; }
    else { lo = q2; clo = c2; }
    for (int it = 0; it < 12 && chi - clo > 24 && hi - lo > 1; ++it) {
        int32_t t = code_of(bracket_tau(lo < 0 ? -1.0f : code_top(lo), code_top(hi), clo,
                                        chi, k));
        t = t <= lo ? lo + 1 : (t >= hi ? hi - 1 : t);
        const __m512i vt = _mm512_set1_epi16((short)t);
        int64_t ct = 0;
        for (int64_t v = 0; v < nv; ++v)
            ct += __builtin_popcount(_mm512_cmple_epu16_mask(
                _mm512_loadu_si512((const void *)(h + 32 * v)), vt));
        if (ct >= k) { hi = t; chi = ct; } else { lo = t; clo = ct; }
    }
    /* codes <= lo are in, lo < code <= hi the middle: 16-bit indices compressed */
    const __m512i vlo = _mm512_set1_epi16((short)(lo < 0 ? 0 : lo));
    const __m512i vhi = _mm512_set1_epi16((short)hi);
    __m512i idx = iota;
    int64_t ca = 0, nm = 0;
    for (int64_t v = 0; v < nv; ++v) {
        const __m512i hv = _mm512_loadu_si512((const void *)(h + 32 * v));
        const __mmask32 ma = lo < 0 ? 0 : _mm512_cmple_epu16_mask(hv, vlo);
        const __mmask32 mb = _mm512_cmple_epu16_mask(hv, vhi) & ~ma;
        /* the in: their indices in the row (a slab's map, else the positions) */
        const __m512i ia = map ? _mm512_loadu_si512((const void *)(map + 32 * v)) : idx;
        _mm512_storeu_si512((void *)(a16 + ca), _mm512_maskz_compress_epi16(ma, ia));
        _mm512_storeu_si512((void *)(b16 + nm), _mm512_maskz_compress_epi16(mb, idx));
        ca += __builtin_popcount(ma);
        nm += __builtin_popcount(mb);
        idx = _mm512_add_epi16(idx, step);
    }
    /* widened 16 at a time: up to 15 past ca, inside the middle's part or the slack */
    for (int64_t j = 0; j < ca; j += 16)
        _mm512_storeu_si512((void *)(row + j), _mm512_cvtepu16_epi32(
            _mm256_loadu_si256((const __m256i *)(a16 + j))));
    for (int64_t j = 0; j < nm; ++j)
        mk[j] = make_key(dist[b16[j]], map ? map[b16[j]] : b16[j]);
    take_middle(mk, nm, k - clo, row + clo);
    return 1;
}


/* pgn_knn's search on 16-bit codes for centres [0, s); sl: the points' slab (pgn_slab.c), or
 * NULL. With sl, a centre first searches the buckets that hold every point within the
 * distance pass's outer count f2 of it (pgn_slab_range: a point's distance, as rounded, is
 * at least its axis offset squared); if k of them are within f2, so are the k nearest.
 * Else it searches all points. */
void pgn_knn_codes(const float *x, const float *y, const float *z, int64_t n,
                      const float *cx, const float *cy, const float *cz, int64_t s, int64_t k,
                      int32_t *nb, float *dist, uint64_t *keys, float guess,
                      const pgn_slab *sl) {
    const int64_t nv = (n + 31) / 32, R = (nv + 1) * 32;  /* codes a region (64-byte sized) */
    uint16_t *h = (uint16_t *)keys, *a16 = h + R, *b16 = a16 + R;
    uint64_t *mk = (uint64_t *)(b16 + R);   /* 6 R + 8 n bytes <= the 16 n + 256 given */
    const float f2 = code_top(code_of(guess * 1.6f));
    for (int64_t c = 0; c < s; ++c) {
        int32_t *row = nb + c * k;
        if (sl) {
            int64_t p0, p1;
            pgn_slab_range(sl, sl->axis == 0 ? cx[c] : (sl->axis == 1 ? cy[c] : cz[c]), f2,
                           &p0, &p1);
            if (p1 - p0 >= k
                && codes_centre(sl->s[0] + p0, sl->s[1] + p0, sl->s[2] + p0, p1 - p0,
                                sl->idx16 + p0, cx[c], cy[c], cz[c], k, row, dist, h, a16, b16,
                                mk, guess, 1))
                continue;
        }
        codes_centre(x, y, z, n, NULL, cx[c], cy[c], cz[c], k, row, dist, h, a16, b16, mk,
                     guess, 0);
    }
}
#endif
