/* Shared by the encoder's C files: pgn_stage_portable.c (portable stage kernels), the ISA
 * kernels (pgn_avx512*.c, pgn_avx2*.c: empty unless the build targets their ISA),
 * pgn_stage_plan.c (a stage's kernel plan), pgn_steps.c (the steps over a range of centres) and
 * pgn_encode.c (one cloud end to end).
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
/* Separable Gaussians pay off from this many centres per axis: stage 2 on where the SIMD
 * builds' stage 1 runs in neighbour lanes; from 4 in the portable build, whose stage 1
 * would otherwise take an exponential a channel. */
#ifndef SEP_MIN_N
#if defined(__AVX512F__) || defined(PGN_AVX2)
#define SEP_MIN_N 36
#else
#define SEP_MIN_N 4
#endif
#endif
static inline int64_t padded(int64_t d) { return (d + PAD - 1) / PAD * PAD; }

static inline float gelu(float x) { return 0.5f * x * (1.0f + erff(x * 0.70710678118654752f)); }

/* gelu over a chunk's output rows, p (n) 64-byte aligned, n a multiple of 16: one vector loop
 * with no scalar remainder, so every value takes the same code whatever the chunking (batch
 * and thread invariance). Zero padding stays 0 (gelu(0) = 0).
 * AVX-512: erf(u), u = |x| / sqrt(2) < 4, by a degree-5 polynomial on each of 16 intervals
 * of width 1/4 (coefficients by interval in the lanes, picked by one permute each), in
 * t = u - the interval's middle; from u = 3.919206, where erf rounds to 1 in float, exactly
 * 1, so that gelu is exactly 0 below about -5.5 (0.99999994 there would leave x 3e-8).
 * Fitted here (least squares, reweighted towards equal ripple) in double: 6e-9 off erf, 6e-8
 * (an ulp near 1) as evaluated in float. Elsewhere libmvec's erff. */
static inline void gelu_rows(float *p, int64_t n) {
    float *q = (float *)__builtin_assume_aligned(p, 64);
#if defined(__AVX512F__)
    static const float C[6][16] __attribute__((aligned(64))) = {
        {0.140316203f, 0.404116899f, 0.623240888f, 0.784075081f, 0.888388216f, 0.948170066f,
         0.978443742f, 0.99199003f, 0.997345984f, 0.999217033f, 0.999794602f, 0.999952137f,
         0.999990106f, 0.999998212f, 0.999999702f, 0.99999994f},
        {1.11088526f, 0.980352819f, 0.763499558f, 0.524745047f, 0.318273962f, 0.170359775f,
         0.0804722533f, 0.0335458256f, 0.0123408195f, 0.004006478f, 0.00114787556f,
         0.000290228665f, 6.47588749e-05f, 1.27518142e-05f, 2.21594314e-06f, 3.39828205e-07f},
        {-0.138857573f, -0.367625475f, -0.477181554f, -0.459150493f, -0.3580603f,
         -0.234247714f, -0.130769402f, -0.0628989935f, -0.0262239985f, -0.00951495953f,
         -0.00301286392f, -0.000834249309f, -0.000202308409f, -4.30168402e-05f,
         -8.02721661e-06f, -1.31555362e-06f},
        {-0.358716458f, -0.234874621f, -0.0556758381f, 0.0929182544f, 0.162449554f,
         0.157938108f, 0.1148424f, 0.067442514f, 0.0330379494f, 0.0137305008f,
         0.00489023048f, 0.00150238292f, 0.000399942335f, 9.25531494e-05f, 1.86645229e-05f,
         3.28613032e-06f},
        {0.0681787878f, 0.165413991f, 0.175493851f, 0.112153247f, 0.0283346921f,
         -0.0299830902f, -0.0493813157f, -0.0421631262f, -0.0264028776f, -0.0132059362f,
         -0.00546693476f, -0.00190853665f, -0.000568221905f, -0.000145342696f,
         -3.21035841e-05f, -6.14643204e-06f},
        {0.103435606f, 0.0453049205f, -0.0269813892f, -0.0666378736f, -0.0610239506f,
         -0.0306492262f, -0.0023271516f, 0.0113089057f, 0.012436958f, 0.00836101267f,
         0.00423904741f, 0.00172976661f, 0.000585305213f, 0.000166981597f, 4.05841092e-05f,
         8.46232342e-06f},
    };
    const __m512 c0 = _mm512_load_ps(C[0]), c1 = _mm512_load_ps(C[1]);
    const __m512 c2 = _mm512_load_ps(C[2]), c3 = _mm512_load_ps(C[3]);
    const __m512 c4 = _mm512_load_ps(C[4]), c5 = _mm512_load_ps(C[5]);
    const __m512 rs2 = _mm512_set1_ps(0.70710678118654752f), half = _mm512_set1_ps(0.5f);
    const __m512 top = _mm512_set1_ps(3.99999976f), four = _mm512_set1_ps(4.0f);
    const __m512 quarter = _mm512_set1_ps(0.25f), eighth = _mm512_set1_ps(0.125f);
    const __m512 sat = _mm512_set1_ps(3.919206f), one = _mm512_set1_ps(1.0f);
    const __m512i sign = _mm512_set1_epi32((int)0x80000000u);
    for (int64_t i = 0; i < n; i += 16) {
        const __m512 x = _mm512_load_ps(q + i);
        const __m512 u = _mm512_min_ps(_mm512_abs_ps(_mm512_mul_ps(x, rs2)), top);
        const __m512i j = _mm512_cvttps_epi32(_mm512_mul_ps(u, four));
        /* the interval's middle j / 4 + 1 / 8, exact; t within +-1 / 8 */
        const __m512 t = _mm512_sub_ps(u, _mm512_fmadd_ps(_mm512_cvtepi32_ps(j), quarter, eighth));
        __m512 e = _mm512_permutexvar_ps(j, c5);
        e = _mm512_fmadd_ps(e, t, _mm512_permutexvar_ps(j, c4));
        e = _mm512_fmadd_ps(e, t, _mm512_permutexvar_ps(j, c3));
        e = _mm512_fmadd_ps(e, t, _mm512_permutexvar_ps(j, c2));
        e = _mm512_fmadd_ps(e, t, _mm512_permutexvar_ps(j, c1));
        e = _mm512_fmadd_ps(e, t, _mm512_permutexvar_ps(j, c0));
        e = _mm512_mask_mov_ps(e, _mm512_cmp_ps_mask(u, sat, _CMP_GE_OQ), one);
        /* erf is odd: x's sign onto e >= 0 */
        e = _mm512_castsi512_ps(_mm512_or_si512(
            _mm512_castps_si512(e), _mm512_and_si512(_mm512_castps_si512(x), sign)));
        const __m512 hx = _mm512_mul_ps(x, half);
        _mm512_store_ps(q + i, _mm512_fmadd_ps(hx, e, hx));
    }
#else
#pragma omp simd simdlen(16)
    for (int64_t i = 0; i < n; ++i) q[i] = gelu(q[i]);
#endif
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
 * error (9.1e-8 in exact arithmetic). p(0) = 1 keeps Gaussians of exact-integer exponent unbiased. */
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

#if defined(__AVX2__)
/* The lanes kernels' reduction (pgn_avx2_neighbour_lanes.c; pgn_avx512_neighbour_lanes.c per 8 channels): 8
 * channels' lane partials V (8, 8) reduced over the lanes: lane c is channel c's max
 * (MAX) or sum. Rounds: 128-bit halves, pairs, neighbours; the last leaves channel 2 j + h
 * in lane 4 h + j, then one permute. */
#define PGN_RED8(NAME, OP)                                                               \
    static inline __m256 NAME(const float *V) {                                         \
        __m256 s[4];                                                                     \
        for (int i = 0; i < 4; ++i) {                                                    \
            const __m256 a = _mm256_load_ps(V + 16 * i), b = _mm256_load_ps(V + 16 * i + 8); \
            s[i] = OP(_mm256_permute2f128_ps(a, b, 0x20), _mm256_permute2f128_ps(a, b, 0x31)); \
        }                                                                                \
        for (int i = 0; i < 2; ++i)                                                      \
            s[i] = OP(_mm256_shuffle_ps(s[2 * i], s[2 * i + 1], 0x44),                   \
                      _mm256_shuffle_ps(s[2 * i], s[2 * i + 1], 0xEE));                  \
        const __m256 t = OP(_mm256_shuffle_ps(s[0], s[1], 0x88),                         \
                            _mm256_shuffle_ps(s[0], s[1], 0xDD));                        \
        return _mm256_permutevar8x32_ps(t, _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7));  \
    }
PGN_RED8(pgn_red8_max, _mm256_max_ps)
PGN_RED8(pgn_red8_add, _mm256_add_ps)
#undef PGN_RED8
#endif

/* Separable Gaussians with neighbours in the lanes (pgn_avx512_neighbour_lanes.c,
 * pgn_avx2_neighbour_lanes.c; the plan and the scratch size in pgn_stage_plan.c): nc Gaussians per axis in nblk blocks of B
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
/* Stage 1 on the initial embedding (the SIMD lanes kernels): the neighbours' rows from
 * their points, not read and transposed. vx then holds the neighbours' points, not their
 * offsets. */
typedef struct {
    const lanes_t *lp;  /* the initial Gaussians' blocks (D / 3 per axis) */
    const float *pts;   /* the stage's points (n, 3): the centres' coordinates */
    float rx;           /* 1 / std of the coordinate offsets */
} lanes_init_t;
/* The body of the lanes kernels' init_rows (pgn_avx512_neighbour_lanes.c,
 * pgn_avx2_neighbour_lanes.c): the initial Gaussians of the three axes of ng groups of L lanes at coordinates w[3 i + a]
 * (clamped to +-W), blockwise U_j = A_m P^l as in the pe chain, the 3 ng chains (at most
 * NVMAX) interleaved; group i's row a n + j (n = lp->nc) at out + L i + (a n + j) stride
 * gets U_j - csub[a n + j] in the lanes of vm[i], else 0, by STORE(p, vm, U, c). V, EXP2,
 * SET1, SUB and MUL: the ISA's vector type, 2^-t and operations. */
#define PGN_INIT_ROWS_BODY(V, L, NVMAX, EXP2, SET1, SUB, MUL, STORE)                    \
    do {                                                                                 \
        const V ql_ = SET1(lp->ql), nh2ql_ = SET1(-lp->h2ql);                            \
        const int64_t n_ = lp->nc, B_ = lp->B, nblk_ = lp->nblk;                         \
        const int nv_ = 3 * ng;                                                          \
        V P_[NVMAX], U_[NVMAX];                                                          \
        for (int v = 0; v < nv_; ++v) P_[v] = EXP2(MUL(nh2ql_, w[v]));                   \
        for (int64_t m = 0; m < nblk_; ++m) {                                            \
            const V bm = SET1(lp->b[m]);                                                 \
            for (int v = 0; v < nv_; ++v) {                                              \
                const V u = SUB(bm, w[v]);                                               \
                U_[v] = EXP2(MUL(MUL(u, u), ql_));                                       \
            }                                                                            \
            const int64_t j0 = m * B_, Lm = n_ - j0 < B_ ? n_ - j0 : B_;                 \
            for (int64_t l = 0; l < Lm; ++l)                                             \
                for (int v = 0; v < nv_; ++v) {                                          \
                    const int i = v / 3;                                                 \
                    const int64_t j = (v - 3 * i) * n_ + j0 + l;                         \
                    STORE(out + (L) * i + j * stride, vm[i], U_[v], csub[j]);            \
                    U_[v] = MUL(U_[v], P_[v]);                                           \
                }                                                                        \
        }                                                                                \
    } while (0)
#if defined(PGN_AVX2)
void pgn_aggregate_neighbour_lanes_avx2(const float *feat, int64_t D, const int64_t *cidx,
                              const int32_t *nb, int64_t S, int64_t K, const float *vx,
                              float r, const lanes_t *lp, const lanes_init_t *ini,
                              float *out, float *scr);
#endif
#if defined(__AVX512F__)
void pgn_aggregate_neighbour_lanes_avx512(const float *feat, int64_t D, const int64_t *cidx,
                                const int32_t *nb, int64_t S, int64_t K, const float *vx,
                                float r, const lanes_t *lp, const lanes_init_t *ini,
                                float *out, float *scr);
#endif

/* pgn_stage_portable.c */
void pgn_sep_prepare(sep_t *fx, const float *v, int64_t K);
void pgn_stage_aggregate(const float *feat, int64_t D, const int64_t *cidx, const int32_t *nb,
                         int64_t S, int64_t K, const float *vx, float r, const float *cc,
                         const int32_t *ax, float q, float *out, float *pe, int64_t PS,
                         float *mx, float *sm, sep_t *fx);
/* pgn_stage_plan.c */
int pgn_sep_ok(int64_t n, double q, int B);
int pgn_sep_plan(int64_t nc, float q, sep_t *fx, float *b, float *C, float *T);

/* pgn_avx512.c */
#if defined(__AVX512F__)
void pgn_aggregate_narrow_avx512(const float *feat, int64_t D, const int64_t *cidx,
                              const int32_t *nb, int64_t S, int64_t K, const float *vx,
                              float r, const float *ccs, const __mmask16 *m1,
                              const __mmask16 *m2, float s, float *out, float *acc);
void pgn_std_centre_avx512(const float *feat, int64_t Dp, const int32_t *nr, int64_t K,
                           const float *cf, float *a1, float *a2);
#endif
/* pgn_avx512_separable.c */
#if defined(__AVX512F__) && defined(__AVX512VL__)
void pgn_aggregate_separable_avx512(const float *feat, int64_t D, const int64_t *cidx,
                              const int32_t *nb, int64_t S, int64_t K, const float *vx,
                              float r, float *out, float *mx, float *sm, float *G, float *Gs,
                              float *rT, float *T2, sep_t *fx);
#endif

#if defined(PGN_AVX2)
/* pgn_avx2.c */
void pgn_aggregate_narrow_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, const float *ccs, const int32_t *lane_axis, float s,
                            float *out, float *acc);
void pgn_aggregate_separable_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, float *out, float *mx, float *sm, float *G, float *RV,
                            float *G2, int32_t *SRC, float *IT, float *T2, sep_t *fx);
/* pgn_avx2_narrow_derived.c */
int pgn_narrow_derived_ok(int64_t D, float q);
void pgn_aggregate_narrow_derived_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, const float *cents, float s, float *out, float *acc);
void pgn_std_centre_avx2(const float *feat, int64_t Dp, const int32_t *nr, int64_t K,
                         const float *cf, float *a1, float *a2);
#endif

#endif
