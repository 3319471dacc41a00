/* Bank scans for point_gn_ros/bank/search.py: one thread, deterministic.
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
 * (what bank/search.py writes: the AVX2 path's int16 pair sums then cannot saturate). */
void pgn_scan_i8(const int8_t *codes, int64_t n, int64_t r, const int8_t *q, int32_t *out) {
#if defined(__AVX512BW__)
    if (r % 32 == 0 && r <= 512) {
        __m512i qv[16];  /* the query widened to int16, 32 lanes a register */
        const int64_t nq = r / 32;
        for (int64_t j = 0; j < nq; ++j)
            qv[j] = _mm512_cvtepi8_epi16(_mm256_loadu_si256((const void *)(q + 32 * j)));
        for (int64_t i = 0; i < n; ++i) {
            const int8_t *row = codes + i * r;
            if (i + 16 < n)     /* as pgn_scan4.c: the hardware prefetchers lag after idle time */
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
    if (nq == 1) {      /* a lone query: the single-query loop (the same sums) */
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

static int cmp_desc(const void *pa, const void *pb) {
    const int64_t a = *(const int64_t *)pa, b = *(const int64_t *)pb;
    return a < b ? 1 : (a > b ? -1 : 0);
}

/* Indices of the m largest of s[0..n) into idx (any order; at the threshold the lowest
 * indices win). One histogram pass over the top bits, then the boundary bucket is
 * sorted. keys: n int64 scratch. Returns min(m, n). */
int64_t pgn_top_m(const int32_t *s, int64_t n, int64_t m, int32_t *idx, int64_t *keys) {
    if (m >= n) {
        for (int64_t i = 0; i < n; ++i) idx[i] = (int32_t)i;
        return n;
    }
    if (m <= 0) return 0;
    int32_t lo = s[0], hi = s[0];
    for (int64_t i = 0; i < n; ++i) { lo = s[i] < lo ? s[i] : lo; hi = s[i] > hi ? s[i] : hi; }
    enum { NBK = 4096 };
    int shift = 0;
    while ((((int64_t)hi - lo) >> shift) >= NBK) ++shift;
    int32_t hist[NBK];
    memset(hist, 0, sizeof(hist));
    for (int64_t i = 0; i < n; ++i) hist[((int64_t)s[i] - lo) >> shift]++;
    int64_t above = 0, b = NBK - 1;
    for (; b > 0 && above + hist[b] < m; --b) above += hist[b];
    /* buckets > b: all in (above of them); bucket b: the best m - above of it */
    int64_t k = 0, ne = 0;
    for (int64_t i = 0; i < n; ++i) {
        const int64_t bi = ((int64_t)s[i] - lo) >> shift;
        if (bi > b) idx[k++] = (int32_t)i;
        else if (bi == b) keys[ne++] = (int64_t)s[i] * 4294967296LL + (0x7fffffff - (int64_t)i);
    }
    qsort(keys, (size_t)ne, sizeof(int64_t), cmp_desc);
    for (int64_t j = 0; k < m && j < ne; ++j) idx[k++] = (int32_t)(0x7fffffff - (keys[j] & 0xffffffff));
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
