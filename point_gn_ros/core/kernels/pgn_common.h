/* Shared by the encoder's C files: pgn_stage.c (portable stage kernels), the ISA kernels
 * (pgn_avx512*.c, pgn_avx2*.c: compiled only where -march=native enables them),
 * pgn_phases.c (the steps over a range of centres) and pgn_encode.c (one cloud end to end).
 * Hashed with the sources for the kernel cache key (kernels/__init__.py).
 */
#ifndef PGN_COMMON_H
#define PGN_COMMON_H

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#if defined(__AVX512F__) || defined(__AVX2__)
#include <immintrin.h>
#endif
/* The AVX2 + FMA kernels (pgn_avx2.c) run where AVX-512 is not targeted. */
#if defined(__AVX2__) && defined(__FMA__) && !defined(__AVX512F__)
#define PGN_AVX2 1
#endif

#define PAD 16
/* Separable Gaussians pay off from this many centres per axis (stage 2 on). */
#ifndef SEP_MIN_N
#define SEP_MIN_N 36
#endif
static inline int64_t padded(int64_t d) { return (d + PAD - 1) / PAD * PAD; }

static inline float gelu(float x) { return 0.5f * x * (1.0f + erff(x * 0.70710678118654752f)); }

/* gelu over a chunk's output rows, p (n) 64-byte aligned, n a multiple of 16: one vector loop
 * (libmvec's erff) with no scalar remainder, so every value takes the same code whatever the
 * chunking (batch and thread invariance). Zero padding stays 0 (gelu(0) = 0). */
static inline void gelu_rows(float *p, int64_t n) {
    float *q = (float *)__builtin_assume_aligned(p, 64);
#pragma omp simd simdlen(16)
    for (int64_t i = 0; i < n; ++i) q[i] = gelu(q[i]);
}

/* Separable Gaussians on a uniform grid of n centres b_0 + j h (j < n):
 * exp(q (b_0 + (8 m + l) h - w)^2) = A_m(w) * T[m][l] * P(w)^l with
 * A_m(w) = exp(q (b_m - w)^2), b_m = b_0 + 8 m h, T[m][l] = exp(2 q l h b_m + q l^2 h^2),
 * P(w) = exp(-2 q h w). w is clamped to [-W, W], W = 1 + sqrt(87 / |q|): beyond it every
 * Gaussian is below 2e-38 either way. pgn_sep_ok() admits only grids where, with blocks of B,
 * every factor and partial product stays inside float range and an underflowing A_m
 * only ever drops values below e^-30. */
typedef struct {
    int64_t n, M;     /* centres per axis, blocks of B */
    int B;            /* block width: 8 (portable and make_pe), 16 (AVX-512 sep_centre16) */
    float q, h2q;     /* q = -1 / (2 sigma^2), h2q = -2 q h */
    float W;          /* clamp for w */
    const float *b;   /* (M,) block base centres */
    const float *T;   /* (M, 8) */
    /* where chain_ok (AVX-512 with B = 16, AVX2 with B = 8): A_{m+1} = A_m C_m P^B with
     * C_m = exp(2 B q h b_m + B^2 q h^2) and P^B = exp(-2 B q h w), so a block's A costs
     * two multiplies instead of an exponential; NULL: each A_m its own exponential */
    const float *C;   /* (M,) */
    float *A;         /* (K * 3, M) scratch */
    float *E;         /* (K * 3, 9) scratch, then room for AVX-512's (K, 16) E16 */
} sep_t;

/* 2^f on [-1/2, 1/2]: degree-5 polynomial with p(0) = 1 exactly, minimax for the relative
 * error (9.1e-8 in exact arithmetic; the degree-6 Taylor form used before had 1.2e-7 and
 * one FMA more). p(0) = 1 keeps Gaussians of exact-integer exponent unbiased. */
#define PGN_EXP2_C0 1.0f
#define PGN_EXP2_C1 0.6931469776023396f
#define PGN_EXP2_C2 0.24022242081246917f
#define PGN_EXP2_C3 0.0555073373969377f
#define PGN_EXP2_C4 0.009671512829242206f
#define PGN_EXP2_C5 0.001326472815781153f

#if defined(__AVX512F__)
/* 2^-t for t >= 0, 16 lanes: t = k - f with k rounded, |f| <= 1/2, the polynomial for
 * 2^f and scalef for the exact 2^-k. */
static inline __m512 exp2_neg_avx512(__m512 t) {
    const __m512 k = _mm512_roundscale_ps(t, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    const __m512 f = _mm512_sub_ps(k, t);
    __m512 p = _mm512_fmadd_ps(_mm512_set1_ps(PGN_EXP2_C5), f, _mm512_set1_ps(PGN_EXP2_C4));
    p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(PGN_EXP2_C3));
    p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(PGN_EXP2_C2));
    p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(PGN_EXP2_C1));
    p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(PGN_EXP2_C0));
    return _mm512_scalef_ps(p, _mm512_sub_ps(_mm512_setzero_ps(), k));
}
#endif

#if defined(PGN_AVX2)
/* 2^-t for t >= 0, 8 lanes, as exp2_neg_avx512. AVX2 has no scalef: 2^-k is applied by
 * subtracting k from the exponent field of 2^f (in [0.70, 1.42]), exact while the result
 * stays normal, so t is clamped at 125 (like exp_fast's e^-87: every value there is below
 * 2e-38, where the oracle's Gaussians are 0 or denormal anyway). */
static inline __m256 exp2_neg_avx2(__m256 t) {
    t = _mm256_min_ps(t, _mm256_set1_ps(125.0f));
    const __m256 k = _mm256_round_ps(t, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    const __m256 f = _mm256_sub_ps(k, t);
    __m256 p = _mm256_fmadd_ps(_mm256_set1_ps(PGN_EXP2_C5), f, _mm256_set1_ps(PGN_EXP2_C4));
    p = _mm256_fmadd_ps(p, f, _mm256_set1_ps(PGN_EXP2_C3));
    p = _mm256_fmadd_ps(p, f, _mm256_set1_ps(PGN_EXP2_C2));
    p = _mm256_fmadd_ps(p, f, _mm256_set1_ps(PGN_EXP2_C1));
    p = _mm256_fmadd_ps(p, f, _mm256_set1_ps(PGN_EXP2_C0));
    const __m256i k23 = _mm256_slli_epi32(_mm256_cvtps_epi32(k), 23);
    return _mm256_castsi256_ps(_mm256_sub_epi32(_mm256_castps_si256(p), k23));
}
#endif

/* Separable Gaussians with neighbours in the lanes (pgn_avx512_lanes.c, pgn_avx2_lanes.c;
 * the plan and the scratch size in pgn_stage.c): nc Gaussians per axis in nblk blocks of B
 * (the last may be shorter) starting at b[m]; T: (nc,), the T_l of Gaussian j = m B + l. */
#define PGN_LANES_MAXC 32
typedef struct {
    int64_t nc, B, nblk;
    float ql, h2ql, W;  /* -q log2(e), -2 q h log2(e), the clamp of sep_t */
    const float *b, *T;
} lanes_t;
int pgn_lanes_plan(int64_t nc, float q, lanes_t *lp, float *b, float *T);
int64_t pgn_lanes_scratch(int64_t K);
void pgn_lanes_scales(const lanes_t *lp, int64_t D2, float r, float *rs, float *ct, float *t2);
#if defined(PGN_AVX2)
void pgn_aggregate_lanes_avx2(const float *feat, int64_t D, const int64_t *cidx,
                              const int32_t *nb, int64_t S, int64_t K, const float *vx,
                              float r, const lanes_t *lp, float *out, float *scr);
#endif
#if defined(__AVX512F__)
#define pgn_aggregate_lanes pgn_aggregate_lanes_avx512
#elif defined(PGN_AVX2)
#define pgn_aggregate_lanes pgn_aggregate_lanes_avx2
#endif
#if defined(__AVX512F__)
void pgn_aggregate_lanes_avx512(const float *feat, int64_t D, const int64_t *cidx,
                                const int32_t *nb, int64_t S, int64_t K, const float *vx,
                                float r, const lanes_t *lp, float *out, float *scr);
#endif

/* pgn_stage.c */
void pgn_sep_prepare(sep_t *fx, const float *v, int64_t K);
void pgn_stage_aggregate(const float *feat, int64_t D, const int64_t *cidx, const int32_t *nb,
                         int64_t S, int64_t K, const float *vx, float r, const float *cc,
                         const int32_t *ax, float q, float *out, float *pe, int64_t PS,
                         float *mx, float *sm, sep_t *fx);
int pgn_sep_ok(int64_t n, double q, int B);

/* pgn_avx512.c */
#if defined(__AVX512F__)
void pgn_aggregate_d32_avx512(const float *feat, int64_t D, const int64_t *cidx,
                              const int32_t *nb, int64_t S, int64_t K, const float *vx,
                              float r, const float *ccs, const __mmask16 *m1,
                              const __mmask16 *m2, float s, float *out, float *acc);
void pgn_std_centre_avx512(const float *feat, int64_t Dp, const int32_t *nr, int64_t K,
                           const float *cf, float *a1, float *a2);
#endif
/* pgn_avx512_sep.c */
#if defined(__AVX512F__) && defined(__AVX512VL__)
void pgn_aggregate_sep_avx512(const float *feat, int64_t D, const int64_t *cidx,
                              const int32_t *nb, int64_t S, int64_t K, const float *vx,
                              float r, float *out, float *mx, float *sm, float *G, float *Gs,
                              float *rT, float *T2, sep_t *fx);
#endif

#if defined(PGN_AVX2)
/* pgn_avx2.c */
void pgn_aggregate_d32_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, const float *ccs, const int32_t *lane_axis, float s,
                            float *out, float *acc);
void pgn_aggregate_sep_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, float *out, float *mx, float *sm, float *G, float *RV,
                            float *G2, int32_t *SRC, float *IT, float *T2, sep_t *fx);
/* pgn_avx2_d18.c */
int pgn_d18_ok(int64_t D, float q);
void pgn_aggregate_d18_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, const float *cents, float s, float *out, float *acc);
void pgn_std_centre_avx2(const float *feat, int64_t Dp, const int32_t *nr, int64_t K,
                         const float *cf, float *a1, float *a2);
#endif

#endif
