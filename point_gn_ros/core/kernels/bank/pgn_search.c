/* Bank scans for point_gn_ros/bank/index.py: one thread, deterministic.
 *
 * pgn_scan_i8: int8 dot products of a query with every code row (the coarse pass of the
 * two-stage search: a quarter of the bytes of float32 at a quarter of the width, so the
 * pass is bound by memory bandwidth at 1/16 of a float32 scan's bytes).
 * pgn_top_m: the m largest scores (any order) by a threshold bracket on their values.
 * pgn_scan_f32: float32 dot products (the exact rescoring and the reference scan).
 * pgn_scan_i8_multi: pgn_scan_i8 for a batch of queries, the rows read once per block of
 * rows (integer sums: the same results as one query at a time, in any batch).
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#if defined(__AVX512BW__) || defined(__AVX2__)
#include <immintrin.h>
#endif

/* out[i] = sum_j codes[i * r + j] * q[j]; codes (n, r) int8, codes and q in [-127, 127]
 * (what bank/index.py writes: the AVX2 path's int16 pair sums then cannot saturate). */
void pgn_scan_i8(const int8_t *codes, int64_t n, int64_t r, const int8_t *q, int32_t *out) {
#if defined(__AVX512BW__)
    if (r % 32 == 0 && r <= 512) {
        __m512i qv[16];  /* the query widened to int16, 32 lanes a register */
        const int64_t nq = r / 32;
        for (int64_t j = 0; j < nq; ++j)
            qv[j] = _mm512_cvtepi8_epi16(_mm256_loadu_si256((const void *)(q + 32 * j)));
        for (int64_t i = 0; i < n; ++i) {
            const int8_t *row = codes + i * r;
            if (i + 16 < n)     /* as pgn_scan_i4.c: the hardware prefetchers lag after idle time */
                for (int64_t o = 0; o < r; o += 64) __builtin_prefetch(row + 16 * r + o);
            __m512i acc = _mm512_setzero_si512(), acc2 = acc;
            int64_t j = 0;
            for (; j + 2 <= nq; j += 2) {
                const __m512i a = _mm512_cvtepi8_epi16(_mm256_loadu_si256((const void *)(row + 32 * j)));
                const __m512i b = _mm512_cvtepi8_epi16(_mm256_loadu_si256((const void *)(row + 32 * j + 32)));
                acc = _mm512_add_epi32(acc, _mm512_madd_epi16(a, qv[j]));
                acc2 = _mm512_add_epi32(acc2, _mm512_madd_epi16(b, qv[j + 1]));
            }
            if (j < nq) {
                const __m512i a = _mm512_cvtepi8_epi16(_mm256_loadu_si256((const void *)(row + 32 * j)));
                acc = _mm512_add_epi32(acc, _mm512_madd_epi16(a, qv[j]));
            }
            out[i] = _mm512_reduce_add_epi32(_mm512_add_epi32(acc, acc2));
        }
        return;
    }
#elif defined(__AVX2__)
    if (r % 32 == 0) {
        /* |c| * (q sign c) summed by byte pairs (vpmaddubsw: <= 2 * 127 * 127, no
         * saturation), then to int32 (vpmaddwd with ones): exact, like the plain loop */
        const __m256i ones = _mm256_set1_epi16(1);
        for (int64_t i = 0; i < n; ++i) {
            const int8_t *row = codes + i * r;
            /* rows ahead, one prefetch per cache line (the pass is bound by memory) */
            if (i + 24 < n)
                for (int64_t o = 0; o < r; o += 64) __builtin_prefetch(row + 24 * r + o);
            __m256i acc = _mm256_setzero_si256();
            for (int64_t j = 0; j < r; j += 32) {
                const __m256i c = _mm256_loadu_si256((const void *)(row + j));
                const __m256i qq = _mm256_loadu_si256((const void *)(q + j));
                const __m256i p = _mm256_maddubs_epi16(_mm256_abs_epi8(c), _mm256_sign_epi8(qq, c));
                acc = _mm256_add_epi32(acc, _mm256_madd_epi16(p, ones));
            }
            const __m128i s = _mm_add_epi32(_mm256_castsi256_si128(acc), _mm256_extracti128_si256(acc, 1));
            const __m128i s2 = _mm_add_epi32(s, _mm_shuffle_epi32(s, 0x4e));
            out[i] = _mm_cvtsi128_si32(_mm_add_epi32(s2, _mm_shuffle_epi32(s2, 0xb1)));
        }
        return;
    }
#endif
    for (int64_t i = 0; i < n; ++i) {
        const int8_t *row = codes + i * r;
        int32_t acc = 0;
#pragma omp simd reduction(+:acc)
        for (int64_t j = 0; j < r; ++j) acc += (int32_t)row[j] * (int32_t)q[j];
        out[i] = acc;
    }
}

/* The coarse pass of a batch: out[b * n + i] = sum_j codes[i * r + j] * q[b * r + j] for
 * b < nq. Rows are walked in blocks that stay in L1 while every query passes over them, so
 * a batch reads the codes from memory once instead of once per query. */
enum { SCAN_BLOCK = 64, SCAN_GROUP = 4 };

void pgn_scan_i8_multi(const int8_t *codes, int64_t n, int64_t r, const int8_t *q,
                       int64_t nq, int32_t *out) {
    if (nq == 1) {      /* one query: the single-query loop (the same sums) */
        pgn_scan_i8(codes, n, r, q, out);
        return;
    }
#if defined(__AVX2__) && !defined(__AVX512BW__)
    if (r % 32 == 0) {
        const __m256i ones = _mm256_set1_epi16(1);
        for (int64_t i0 = 0; i0 < n; i0 += SCAN_BLOCK) {
            const int64_t i1 = i0 + SCAN_BLOCK < n ? i0 + SCAN_BLOCK : n;
            for (int64_t b0 = 0; b0 < nq; b0 += SCAN_GROUP) {
                const int64_t g = nq - b0 < SCAN_GROUP ? nq - b0 : SCAN_GROUP;
                const int8_t *qb = q + b0 * r;
                for (int64_t i = i0; i < i1; ++i) {
                    const int8_t *row = codes + i * r;
                    if (b0 == 0 && i + 24 < n)      /* the first group reads from memory */
                        for (int64_t o = 0; o < r; o += 64) __builtin_prefetch(row + 24 * r + o);
                    __m256i acc[SCAN_GROUP];
                    for (int t = 0; t < SCAN_GROUP; ++t) acc[t] = _mm256_setzero_si256();
                    for (int64_t j = 0; j < r; j += 32) {
                        const __m256i c = _mm256_loadu_si256((const void *)(row + j));
                        const __m256i a = _mm256_abs_epi8(c);
                        for (int64_t t = 0; t < g; ++t) {
                            const __m256i qq = _mm256_loadu_si256((const void *)(qb + t * r + j));
                            const __m256i p = _mm256_maddubs_epi16(a, _mm256_sign_epi8(qq, c));
                            acc[t] = _mm256_add_epi32(acc[t], _mm256_madd_epi16(p, ones));
                        }
                    }
                    for (int64_t t = 0; t < g; ++t) {
                        const __m128i s = _mm_add_epi32(_mm256_castsi256_si128(acc[t]),
                                                        _mm256_extracti128_si256(acc[t], 1));
                        const __m128i s2 = _mm_add_epi32(s, _mm_shuffle_epi32(s, 0x4e));
                        out[(b0 + t) * n + i] =
                            _mm_cvtsi128_si32(_mm_add_epi32(s2, _mm_shuffle_epi32(s2, 0xb1)));
                    }
                }
            }
        }
        return;
    }
#endif
    /* elsewhere: pgn_scan_i8 per query over each block (AVX-512BW reads the block from L1) */
    for (int64_t i0 = 0; i0 < n; i0 += SCAN_BLOCK) {
        const int64_t m = n - i0 < SCAN_BLOCK ? n - i0 : SCAN_BLOCK;
        for (int64_t b = 0; b < nq; ++b)
            pgn_scan_i8(codes + i0 * r, m, r, q + b * r, out + b * n + i0);
    }
}

/* How many of s[0..n) are >= t (a vector compare and count; no branches). */
static int64_t count_ge(const int32_t *s, int64_t n, int32_t t) {
    int32_t c = 0;                       /* 32-bit lanes: 16 a vector (n < 2^31) */
#pragma omp simd reduction(+:c)
    for (int64_t i = 0; i < n; ++i) c += s[i] >= t;
    return c;
}

/* Indices i with s[i] >= t into out, ascending (returns how many). */
static int64_t indices_ge(const int32_t *s, int64_t n, int32_t t, int32_t *out) {
    int64_t k = 0, i = 0;
#if defined(__AVX512F__)
    /* 16 at a time, compressed into a register and stored whole: a store at out + k with
     * k <= i writes below out + i + 16 <= out + n, so out needs no slack past n */
    const __m512i vt = _mm512_set1_epi32(t), step = _mm512_set1_epi32(16);
    __m512i iv = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    for (; i + 16 <= n; i += 16) {
        const __mmask16 mk = _mm512_cmpge_epi32_mask(_mm512_loadu_si512((const void *)(s + i)), vt);
        if (mk) {
            _mm512_storeu_si512((void *)(out + k), _mm512_maskz_compress_epi32(mk, iv));
            k += __builtin_popcount(mk);
        }
        iv = _mm512_add_epi32(iv, step);
    }
#endif
    for (; i < n; ++i)
        if (s[i] >= t) out[k++] = (int32_t)i;
    return k;
}

/* Indices of the m largest of s[0..n) into idx, in ascending index order; at the threshold
 * the lowest indices win. A threshold t with m <= count(s >= t) is bracketed by counting
 * passes (interpolated towards m + m/4, as the kNN brackets its k-th distance), the
 * indices at or above it are gathered in one pass, and the exact m-th value is found among
 * those few by bisection. Every pass is a vector compare over the scores: the histogram
 * keys: n int64 of scratch (the gathered indices and their scores, n int32 each).
 * Returns min(m, n). */
int64_t pgn_top_m(const int32_t *s, int64_t n, int64_t m, int32_t *idx, int64_t *keys) {
    if (m >= n) {
        for (int64_t i = 0; i < n; ++i) idx[i] = (int32_t)i;
        return n;
    }
    if (m <= 0) return 0;
    int32_t lo = s[0], hi = s[0];
#pragma omp simd reduction(min:lo) reduction(max:hi)
    for (int64_t i = 0; i < n; ++i) { lo = s[i] < lo ? s[i] : lo; hi = s[i] > hi ? s[i] : hi; }
    /* invariant: count(s >= lo) = clo >= m > chi = count(s >= top) */
    int64_t clo = n, chi = 0;
    int64_t top = hi + 1LL;
    const int64_t want = m + m / 4;      /* aim a little above m: the gather stays small */
    for (int it = 0; it < 40 && top - lo > 1 && clo > 2 * m + 64; ++it) {
        const double f = (double)(want - chi) / (double)(clo - chi);   /* in (0, 1) */
        int64_t t = top - (int64_t)((double)(top - lo) * f);
        const int64_t step = (top - lo) / 10;   /* never shrink the bracket by less */
        t = t < lo + step ? lo + step : (t > top - step ? top - step : t);
        t = t <= lo ? lo + 1 : (t >= top ? top - 1 : t);
        const int64_t c = count_ge(s, n, (int32_t)t);
        if (c >= m) { lo = (int32_t)t; clo = c; } else { top = t; chi = c; }
    }
    int32_t *cand = (int32_t *)keys, *val = cand + n;
    const int64_t nc = indices_ge(s, n, lo, cand);
    for (int64_t j = 0; j < nc; ++j) val[j] = s[cand[j]];
    /* the m-th largest value v among the candidates: count(>= v) >= m > count(>= v + 1) */
    int64_t a = lo, b = top;                 /* count(>= a) >= m, count(>= b) < m */
    while (b - a > 1) {
        const int64_t t = a + (b - a) / 2;
        if (count_ge(val, nc, (int32_t)t) >= m) a = t; else b = t;
    }
    const int32_t v = (int32_t)a;
    int64_t ties = m - (a < INT32_MAX ? count_ge(val, nc, (int32_t)(a + 1)) : 0), k = 0;
    for (int64_t j = 0; j < nc; ++j)          /* at v, the lowest indices */
        if (val[j] > v || (val[j] == v && ties-- > 0)) idx[k++] = cand[j];
    return k;
}

/* out[t] = sum_j feats[rows[t] * d + j] * q[j] for t < m (rows NULL: all n = m rows). */
void pgn_scan_f32(const float *feats, int64_t d, const int32_t *rows, int64_t m,
                  const float *q, float *out) {
    for (int64_t t = 0; t < m; ++t) {
        const float *row = feats + (rows ? (int64_t)rows[t] : t) * d;
        float acc = 0.0f;
#pragma omp simd reduction(+:acc)
        for (int64_t j = 0; j < d; ++j) acc += row[j] * q[j];
        out[t] = acc;
    }
}
