/* Micro-benchmarks for the roofline table of `point_gn bench --profile`: what one core of
 * this machine can do at best, measured in the same run as the phases they bound.
 *
 * Compiled without fast-math (which would let the compiler merge or reassociate the
 * chains that are being timed). Each function does a fixed
 * amount of work and returns how much (lane operations, exps, bytes); the caller times
 * it with the calling thread's CPU clock. Results are returned so nothing is optimised
 * away. AVX-512 intrinsics where the compiler targets them (the encoder's own hot loops
 * use them there too), plain vectorisable C elsewhere.
 */
#include <stdint.h>
#include <string.h>
#if defined(__AVX512F__) || defined(__AVX2__)
#include <immintrin.h>
#endif
/* the AVX2 + FMA kernels (pgn_avx2.c) run where AVX-512 is not targeted: time those */
#if defined(__AVX2__) && defined(__FMA__) && !defined(__AVX512F__)
#define PGN_PEAK_AVX2 1
#endif

static volatile float pgn_peak_sink;

/* fp32 lane operations: 8 independent FMA chains and 8 add chains interleaved (the mix of
 * the encoder's inner loops: multiply-adds, adds and maxima issue on different pipes).
 * An FMA counts as one operation. Returns the number of lane operations done. */
double pgn_peak_ops(int64_t iters) {
#if defined(__AVX512F__)
    const __m512 m = _mm512_set1_ps(0.999999f), c = _mm512_set1_ps(1e-7f);
    /* distinct starting values, or the compiler merges identical chains */
    __m512 a0 = _mm512_set1_ps(1.0f), a1 = _mm512_set1_ps(1.1f), a2 = _mm512_set1_ps(1.2f),
           a3 = _mm512_set1_ps(1.3f), a4 = _mm512_set1_ps(1.4f), a5 = _mm512_set1_ps(1.5f),
           a6 = _mm512_set1_ps(1.6f), a7 = _mm512_set1_ps(1.7f);
    __m512 s0 = _mm512_set1_ps(0.1f), s1 = _mm512_set1_ps(0.2f), s2 = _mm512_set1_ps(0.3f),
           s3 = _mm512_set1_ps(0.4f), s4 = _mm512_set1_ps(0.5f), s5 = _mm512_set1_ps(0.6f),
           s6 = _mm512_set1_ps(0.7f), s7 = _mm512_set1_ps(0.8f);
    for (int64_t i = 0; i < iters; ++i) {
        a0 = _mm512_fmadd_ps(a0, m, c); s0 = _mm512_add_ps(s0, a7);
        a1 = _mm512_fmadd_ps(a1, m, c); s1 = _mm512_add_ps(s1, a0);
        a2 = _mm512_fmadd_ps(a2, m, c); s2 = _mm512_add_ps(s2, a1);
        a3 = _mm512_fmadd_ps(a3, m, c); s3 = _mm512_add_ps(s3, a2);
        a4 = _mm512_fmadd_ps(a4, m, c); s4 = _mm512_add_ps(s4, a3);
        a5 = _mm512_fmadd_ps(a5, m, c); s5 = _mm512_add_ps(s5, a4);
        a6 = _mm512_fmadd_ps(a6, m, c); s6 = _mm512_add_ps(s6, a5);
        a7 = _mm512_fmadd_ps(a7, m, c); s7 = _mm512_add_ps(s7, a6);
    }
    __m512 t = _mm512_add_ps(_mm512_add_ps(_mm512_add_ps(s0, s1), _mm512_add_ps(s2, s3)),
                             _mm512_add_ps(_mm512_add_ps(s4, s5), _mm512_add_ps(s6, s7)));
    pgn_peak_sink = _mm512_reduce_add_ps(t);
    return (double)iters * 16.0 * 16.0;
#elif defined(PGN_PEAK_AVX2)
    const __m256 m = _mm256_set1_ps(0.999999f), c = _mm256_set1_ps(1e-7f);
    __m256 a0 = _mm256_set1_ps(1.0f), a1 = _mm256_set1_ps(1.1f), a2 = _mm256_set1_ps(1.2f),
           a3 = _mm256_set1_ps(1.3f), a4 = _mm256_set1_ps(1.4f), a5 = _mm256_set1_ps(1.5f),
           a6 = _mm256_set1_ps(1.6f), a7 = _mm256_set1_ps(1.7f);
    __m256 s0 = _mm256_set1_ps(0.1f), s1 = _mm256_set1_ps(0.2f), s2 = _mm256_set1_ps(0.3f),
           s3 = _mm256_set1_ps(0.4f), s4 = _mm256_set1_ps(0.5f), s5 = _mm256_set1_ps(0.6f),
           s6 = _mm256_set1_ps(0.7f), s7 = _mm256_set1_ps(0.8f);
    for (int64_t i = 0; i < iters; ++i) {
        a0 = _mm256_fmadd_ps(a0, m, c); s0 = _mm256_add_ps(s0, a7);
        a1 = _mm256_fmadd_ps(a1, m, c); s1 = _mm256_add_ps(s1, a0);
        a2 = _mm256_fmadd_ps(a2, m, c); s2 = _mm256_add_ps(s2, a1);
        a3 = _mm256_fmadd_ps(a3, m, c); s3 = _mm256_add_ps(s3, a2);
        a4 = _mm256_fmadd_ps(a4, m, c); s4 = _mm256_add_ps(s4, a3);
        a5 = _mm256_fmadd_ps(a5, m, c); s5 = _mm256_add_ps(s5, a4);
        a6 = _mm256_fmadd_ps(a6, m, c); s6 = _mm256_add_ps(s6, a5);
        a7 = _mm256_fmadd_ps(a7, m, c); s7 = _mm256_add_ps(s7, a6);
    }
    __m256 t = _mm256_add_ps(_mm256_add_ps(_mm256_add_ps(s0, s1), _mm256_add_ps(s2, s3)),
                             _mm256_add_ps(_mm256_add_ps(s4, s5), _mm256_add_ps(s6, s7)));
    float lanes[8];
    _mm256_storeu_ps(lanes, t);
    pgn_peak_sink = lanes[0] + lanes[1] + lanes[2] + lanes[3] + lanes[4] + lanes[5] + lanes[6]
                    + lanes[7];
    return (double)iters * 16.0 * 8.0;
#else
    float a[8][8], s[8][8];
    for (int j = 0; j < 8; ++j)
        for (int l = 0; l < 8; ++l) { a[j][l] = 1.0f + 0.1f * j + 0.01f * l; s[j][l] = 0.0f; }
    for (int64_t i = 0; i < iters; ++i) {
        for (int j = 0; j < 8; ++j) {
#pragma omp simd
            for (int l = 0; l < 8; ++l) {
                a[j][l] = a[j][l] * 0.999999f + 1e-7f;
                s[j][l] += a[(j + 7) % 8][l];
            }
        }
    }
    float t = 0.0f;
    for (int j = 0; j < 8; ++j)
        for (int l = 0; l < 8; ++l) t += s[j][l];
    pgn_peak_sink = t;
    return (double)iters * 8.0 * 8.0 * 2.0;
#endif
}

/* exp(x) as the encoder evaluates it (2^x by rounding, a degree-5 polynomial and an exact
 * power of two), over an L1-resident block, vectorised. Returns the number of exps. */
double pgn_peak_exp(int64_t iters) {
    enum { NB = 1024 };
    float x[NB] __attribute__((aligned(64))), y[NB] __attribute__((aligned(64)));
    for (int i = 0; i < NB; ++i) x[i] = -20.0f * (float)i / NB;
    float acc = 0.0f;
    for (int64_t it = 0; it < iters; ++it) {
        x[it % NB] -= 1e-6f;  /* a dependency, so the loop is not hoisted */
#if defined(__AVX512F__)
        /* as aggregate_d32_avx512 does it: scalef applies 2^k */
        const __m512 l2e = _mm512_set1_ps(1.44269504088896341f);
        for (int i = 0; i < NB; i += 16) {
            const __m512 t = _mm512_mul_ps(_mm512_load_ps(x + i), l2e);
            const __m512 k = _mm512_roundscale_ps(t, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
            const __m512 f = _mm512_sub_ps(t, k);
            __m512 p = _mm512_fmadd_ps(_mm512_set1_ps(0.001326472815781153f), f, _mm512_set1_ps(0.009671512829242206f));
            p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(0.0555073373969377f));
            p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(0.24022242081246917f));
            p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(0.6931469776023396f));
            p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(1.0f));
            _mm512_store_ps(y + i, _mm512_scalef_ps(p, k));
        }
        acc += y[it % NB];
        continue;
#elif defined(PGN_PEAK_AVX2)
        /* as pgn_avx2.c does it (exp2_neg_avx2): the power of two built in the exponent */
        const __m256 l2e = _mm256_set1_ps(1.44269504088896341f);
        for (int i = 0; i < NB; i += 8) {
            const __m256 t = _mm256_mul_ps(_mm256_load_ps(x + i), l2e);
            const __m256 k = _mm256_round_ps(t, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
            const __m256 f = _mm256_sub_ps(t, k);
            __m256 p = _mm256_fmadd_ps(_mm256_set1_ps(0.001326472815781153f), f, _mm256_set1_ps(0.009671512829242206f));
            p = _mm256_fmadd_ps(p, f, _mm256_set1_ps(0.0555073373969377f));
            p = _mm256_fmadd_ps(p, f, _mm256_set1_ps(0.24022242081246917f));
            p = _mm256_fmadd_ps(p, f, _mm256_set1_ps(0.6931469776023396f));
            p = _mm256_fmadd_ps(p, f, _mm256_set1_ps(1.0f));
            const __m256i e = _mm256_slli_epi32(
                _mm256_add_epi32(_mm256_cvtps_epi32(k), _mm256_set1_epi32(127)), 23);
            _mm256_store_ps(y + i, _mm256_mul_ps(p, _mm256_castsi256_ps(e)));
        }
        acc += y[it % NB];
        continue;
#endif
#pragma omp simd
        for (int i = 0; i < NB; ++i) {
            const float t = x[i] * 1.44269504088896341f;
            const float k = __builtin_roundf(t), f = t - k;
            float p = 0.001326472815781153f;
            p = p * f + 0.009671512829242206f;
            p = p * f + 0.0555073373969377f;
            p = p * f + 0.24022242081246917f;
            p = p * f + 0.6931469776023396f;
            p = p * f + 1.0f;
            const int32_t bits = ((int32_t)k + 127) << 23;
            float sc;
            memcpy(&sc, &bits, 4);
            y[i] = p * sc;
        }
        acc += y[it % NB];
    }
    pgn_peak_sink = acc;
    return (double)iters * NB;
}

/* Read bandwidth: sums n floats (64-byte aligned, n a multiple of 64) reps times with
 * independent accumulators. Returns the bytes read. */
double pgn_peak_read(const float *buf, int64_t n, int64_t reps) {
#if defined(__AVX512F__)
    __m512 s0 = _mm512_setzero_ps(), s1 = s0, s2 = s0, s3 = s0;
    for (int64_t r = 0; r < reps; ++r) {
        for (int64_t i = 0; i < n; i += 64) {
            s0 = _mm512_add_ps(s0, _mm512_load_ps(buf + i));
            s1 = _mm512_add_ps(s1, _mm512_load_ps(buf + i + 16));
            s2 = _mm512_add_ps(s2, _mm512_load_ps(buf + i + 32));
            s3 = _mm512_add_ps(s3, _mm512_load_ps(buf + i + 48));
        }
    }
    pgn_peak_sink = _mm512_reduce_add_ps(_mm512_add_ps(_mm512_add_ps(s0, s1),
                                                       _mm512_add_ps(s2, s3)));
#elif defined(PGN_PEAK_AVX2)
    __m256 s0 = _mm256_setzero_ps(), s1 = s0, s2 = s0, s3 = s0;
    __m256 s4 = s0, s5 = s0, s6 = s0, s7 = s0;
    for (int64_t r = 0; r < reps; ++r) {
        for (int64_t i = 0; i < n; i += 64) {
            s0 = _mm256_add_ps(s0, _mm256_load_ps(buf + i));
            s1 = _mm256_add_ps(s1, _mm256_load_ps(buf + i + 8));
            s2 = _mm256_add_ps(s2, _mm256_load_ps(buf + i + 16));
            s3 = _mm256_add_ps(s3, _mm256_load_ps(buf + i + 24));
            s4 = _mm256_add_ps(s4, _mm256_load_ps(buf + i + 32));
            s5 = _mm256_add_ps(s5, _mm256_load_ps(buf + i + 40));
            s6 = _mm256_add_ps(s6, _mm256_load_ps(buf + i + 48));
            s7 = _mm256_add_ps(s7, _mm256_load_ps(buf + i + 56));
        }
    }
    float lanes[8];
    _mm256_storeu_ps(lanes, _mm256_add_ps(_mm256_add_ps(_mm256_add_ps(s0, s1), _mm256_add_ps(s2, s3)),
                                          _mm256_add_ps(_mm256_add_ps(s4, s5), _mm256_add_ps(s6, s7))));
    pgn_peak_sink = lanes[0] + lanes[1] + lanes[2] + lanes[3] + lanes[4] + lanes[5] + lanes[6]
                    + lanes[7];
#else
    float s[64] = {0};
    for (int64_t r = 0; r < reps; ++r)
        for (int64_t i = 0; i < n; i += 64) {
#pragma omp simd
            for (int l = 0; l < 64; ++l) s[l] += buf[i + l];
        }
    float t = 0.0f;
    for (int l = 0; l < 64; ++l) t += s[l];
    pgn_peak_sink = t;
#endif
    return (double)n * 4.0 * (double)reps;
}
