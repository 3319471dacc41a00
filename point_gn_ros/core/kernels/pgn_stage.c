/* Point-GN encoder, one cloud at a time, fused: no (S, k, D) tensor is ever built.
 *
 * Compiled with -O3 -march=native -ffast-math (vectorised expf from glibc's
 * libmvec); the geometry (FPS, kNN) lives in pgn_geom.c, compiled without
 * fast-math so neighbour choices match the oracle exactly. Results are a pure
 * function of one cloud, whatever the batch or thread, so batches are invariant.
 */
#include <math.h>
#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#if defined(__AVX512F__)
#include <immintrin.h>
#endif

void pgn_fps(const float *xyz, const float *x, const float *y, const float *z, int64_t n,
             int64_t m, int64_t *idx, float *min_d);
void pgn_knn(const float *x, const float *y, const float *z, int64_t n, const float *cx,
             const float *cy, const float *cz, int64_t s, int64_t k, int32_t *nb, float *dist,
             uint64_t *keys);

int pgn_abi_version(void) { return 1; }

#ifdef PGN_PROFILE
#include <time.h>
double pgn_prof[16];  /* per-phase thread CPU seconds; slots: bench_cmd.PROFILE_SLOTS */
static double now(void) { struct timespec ts; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts); return ts.tv_sec + 1e-9 * ts.tv_nsec; }
#define TIC(i) double _t##i = now()
#define TOC(i, slot) pgn_prof[slot] += now() - _t##i
#else
#define TIC(i)
#define TOC(i, slot)
#endif

typedef struct {
    int64_t num_points, init_dim, stages, k;
    float sigma;
} pgn_cfg;

/* exp(x) for x in [-87, 87] (callers clamp): Cody-Waite range reduction and a
 * degree-6 polynomial, relative error < 2e-7. Inline and branch-free, so the
 * pe loop vectorises without library calls or special-case lanes. */
static inline float exp_fast(float x) {
    const float kf = __builtin_roundf(x * 1.44269504088896341f);
    float r = x - kf * 0.693145751953125f;
    r = r - kf * 1.428606765330187e-06f;
    float p = 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    const int32_t bits = ((int32_t)kf + 127) << 23;
    float scale;
    memcpy(&scale, &bits, 4);
    return p * scale;
}

static inline float gelu(float x) { return 0.5f * x * (1.0f + erff(x * 0.70710678118654752f)); }

/* Gaussian positional encoding of v (3 values) into pe[0..3n): axis blocks of n. */
static inline void gpe3(const float *v, const float *cent, int64_t n, float q, float *pe) {
    for (int a = 0; a < 3; ++a) {
        const float va = v[a];
        float *o = pe + a * n;
#pragma omp simd
        for (int64_t j = 0; j < n; ++j) {
            float u = cent[j] - va;
            o[j] = expf(q * u * u);
        }
    }
}

#define PAD 16
/* Separable Gaussians pay off from this many centres per axis (stage 2 on). */
#ifndef SEP_MIN_N
#define SEP_MIN_N 36
#endif
static inline int64_t padded(int64_t d) { return (d + PAD - 1) / PAD * PAD; }

static void *xalloc(size_t bytes) {
    /* 64-byte aligned, zeroed: padding lanes stay 0 (they enter sums as 0 - 0) */
    size_t sz = (bytes + 63) / 64 * 64;
    void *p = aligned_alloc(64, sz ? sz : 64);
    if (p) memset(p, 0, sz ? sz : 64);
    return p;
}

/* Separable Gaussians on a uniform grid of n centres b_0 + j h (j < n):
 * exp(q (b_0 + (8 m + l) h - w)^2) = A_m(w) * T[m][l] * P(w)^l with
 * A_m(w) = exp(q (b_m - w)^2), b_m = b_0 + 8 m h, T[m][l] = exp(2 q l h b_m + q l^2 h^2),
 * P(w) = exp(-2 q h w). w is clamped to [-W, W], W = 1 + sqrt(87 / |q|): beyond it every
 * Gaussian is below 2e-38 either way. sep_ok() admits only grids where, with blocks of 8,
 * every factor and partial product stays inside float range and an underflowing A_m
 * only ever drops values below e^-30. */
typedef struct {
    int64_t n, M;     /* centres per axis, blocks of B */
    int B;            /* block width: 8 (portable and make_pe), 16 (AVX-512 sep_pass16) */
    float q, h2q;     /* q = -1 / (2 sigma^2), h2q = -2 q h */
    float W;          /* clamp for w */
    const float *b;   /* (M,) block base centres */
    const float *T;   /* (M, 8) */
    float *A;         /* (K * 3, M) scratch */
    float *E;         /* (K * 3, 8) scratch */
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

/* A and E for one centre's K neighbours, v (K, 3) normalised offsets; stored
 * neighbour-axis minor (A[m][ta], E[l][ta], ta = 3 t + a) so every loop here runs
 * vectorised across the 3 K (t, a) pairs. */
static void sep_prepare(sep_t *fx, const float *v, int64_t K) {
    const int64_t M = fx->M, nta = K * 3;
    float *w = fx->E;  /* row 0 of E (all ones) is filled last: use it for w meanwhile */
    const float W = fx->W;
#pragma omp simd
    for (int64_t i = 0; i < nta; ++i) w[i] = v[i] < -W ? -W : (v[i] > W ? W : v[i]);
    for (int64_t m = 0; m < M; ++m) {
        const float bm = fx->b[m], q = fx->q;
        float *A = fx->A + m * nta;
#if defined(__AVX512F__)
        /* 16 lanes: 2^-(u^2 |q| log2 e) by rounding + polynomial + scalef (as in
         * aggregate_d32_avx512), the exponent clamped like exp_fast's -87 */
        const __m512 vb = _mm512_set1_ps(bm), vs = _mm512_set1_ps(-q * 1.44269504088896341f);
        const __m512 tmax = _mm512_set1_ps(87.0f * 1.44269504088896341f);
        for (int64_t i = 0; i < nta; i += 16) {
            const __mmask16 k = nta - i >= 16 ? (__mmask16)0xffff
                                              : (__mmask16)((1u << (nta - i)) - 1u);
            const __m512 u = _mm512_sub_ps(vb, _mm512_maskz_loadu_ps(k, w + i));
            const __m512 t = _mm512_min_ps(_mm512_mul_ps(_mm512_mul_ps(u, u), vs), tmax);
            _mm512_mask_storeu_ps(A + i, k, exp2_neg_avx512(t));
        }
        continue;
#endif
#pragma omp simd
        for (int64_t i = 0; i < nta; ++i) {
            const float u = bm - w[i];
            const float e = q * u * u;
            A[i] = exp_fast(e > -87.0f ? e : -87.0f);
        }
    }
    float *E = fx->E;
    const float h2q = fx->h2q;
    if (fx->B == 16) {  /* P, P^2, P^4, P^8: sep_pass16 builds the 16 powers */
#pragma omp simd
        for (int64_t i = 0; i < nta; ++i) {
            const float p1 = exp_fast(h2q * w[i]), p2 = p1 * p1, p4 = p2 * p2;
            E[1 * nta + i] = p1; E[2 * nta + i] = p2; E[4 * nta + i] = p4;
            E[8 * nta + i] = p4 * p4;
        }
        return;
    }
#pragma omp simd
    for (int64_t i = 0; i < nta; ++i) {
        const float p1 = exp_fast(h2q * w[i]), p2 = p1 * p1, p4 = p2 * p2;
        E[1 * nta + i] = p1; E[2 * nta + i] = p2; E[3 * nta + i] = p2 * p1;
        E[4 * nta + i] = p4; E[5 * nta + i] = p4 * p1; E[6 * nta + i] = p4 * p2;
        E[7 * nta + i] = p4 * (p2 * p1);
    }
#pragma omp simd
    for (int64_t i = 0; i < nta; ++i) E[i] = 1.0f;
}

/* pe (2D channels, axis blocks of n) of neighbour t of the current centre. */
static inline void make_pe(int64_t t, const float *v, int64_t npe, const float *cc,
                           const int32_t *ax, float q, const sep_t *fx, int64_t K, float *pe) {
    if (fx) {
        /* separable Gaussians: pe[a n + 8 m + l] = A[t, a, m] * T[m, l] * P[t, a]^l.
         * Blocks of 8 may spill into the next axis; axes are written in order so
         * each spill is overwritten by the right values. */
        const int64_t nta = K * 3;
        for (int a = 0; a < 3; ++a) {
            const int64_t ta = t * 3 + a;
            float e[8];
            for (int l = 0; l < 8; ++l) e[l] = fx->E[l * nta + ta];
            float *o = pe + a * fx->n;
            for (int64_t m = 0; m < fx->M; ++m) {
                const float am = fx->A[m * nta + ta];
                const float *T = fx->T + m * 8;
#pragma omp simd
                for (int l = 0; l < 8; ++l) o[m * 8 + l] = am * (T[l] * e[l]);
            }
        }
    } else {
        const float v0 = v[0], v1 = v[1], v2 = v[2];
        /* pe channel d: Gaussian of axis ax[d] around cc[d] */
#pragma omp simd aligned(pe, cc, ax : 64)
        for (int64_t d = 0; d < npe; ++d) {
            const float va = ax[d] == 0 ? v0 : (ax[d] == 1 ? v1 : v2);
            const float u = cc[d] - va;
            const float e = q * u * u;  /* clamp: below -87 the value is < 2e-38 anyway */
            pe[d] = exp_fast(e > -87.0f ? e : -87.0f);
        }
    }
}

/* One stage's neighbourhood aggregation, all S centres.
 * feat: (n_prev, Dp) features (row stride Dp = padded(D), zero padding); cidx: (S,);
 * nb: (S, K); vx: (S, K, 3) normalised offsets; r = 1 / (std(dfeat) + 1e-5);
 * cc, ax: per-channel Gaussian centre and axis for the 2D = 3n pe channels (padded);
 * out: (S, D2p) with D2p = padded(2D), padding written as 0.
 * pe: 4 buffers of PS floats (PS >= padded(D + Dp) + 16); mx, sm (>= 2 Dp): scratch.
 * (row - cf) * r, not row * r - cf * r: identical points must give exactly 0 even
 * when r = 1e5 (zero spread). fx: separable Gaussians, or NULL for direct evaluation (cheaper for small n).
 * Neighbours go 4 at a time so the running max and sum are loaded and stored once
 * per 4 neighbours. */
static void stage_aggregate(const float *feat, int64_t D, const int64_t *cidx, const int32_t *nb,
                            int64_t S, int64_t K, const float *vx, float r, const float *cc,
                            const int32_t *ax, float q, float *out, float *pe, int64_t PS,
                            float *mx, float *sm, sep_t *fx) {
    const int64_t Dp = padded(D), D2 = 2 * D, D2p = padded(D2), npe = padded(D + Dp);
    const float invk = 1.0f / (float)K;
    float *mx2 = mx + Dp, *sm2 = sm + Dp;
    float *pe0 = pe, *pe1 = pe + PS, *pe2 = pe + 2 * PS, *pe3 = pe + 3 * PS;
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const int32_t *nr = nb + c * K;
        const float *vc = vx + c * K * 3;
        for (int64_t d = 0; d < 2 * Dp; ++d) { mx[d] = -INFINITY; sm[d] = 0.0f; }
        if (fx) sep_prepare(fx, vc, K);
        int64_t t = 0;
        for (; t + 4 <= K; t += 4) {
            make_pe(t, vc + t * 3, npe, cc, ax, q, fx, K, pe0);
            make_pe(t + 1, vc + t * 3 + 3, npe, cc, ax, q, fx, K, pe1);
            make_pe(t + 2, vc + t * 3 + 6, npe, cc, ax, q, fx, K, pe2);
            make_pe(t + 3, vc + t * 3 + 9, npe, cc, ax, q, fx, K, pe3);
            const float *r0 = feat + (int64_t)nr[t] * Dp, *r1 = feat + (int64_t)nr[t + 1] * Dp;
            const float *r2 = feat + (int64_t)nr[t + 2] * Dp, *r3 = feat + (int64_t)nr[t + 3] * Dp;
#pragma omp simd aligned(r0, r1, r2, r3, cf, pe0, pe1, pe2, pe3, mx, sm : 64)
            for (int64_t d = 0; d < Dp; ++d) {
                const float p0 = pe0[d], p1 = pe1[d], p2 = pe2[d], p3 = pe3[d];
                const float w0 = ((r0[d] - cf[d]) * r + p0) * p0;
                const float w1 = ((r1[d] - cf[d]) * r + p1) * p1;
                const float w2 = ((r2[d] - cf[d]) * r + p2) * p2;
                const float w3 = ((r3[d] - cf[d]) * r + p3) * p3;
                const float a01 = w0 > w1 ? w0 : w1, a23 = w2 > w3 ? w2 : w3;
                const float m = a01 > a23 ? a01 : a23;
                mx[d] = m > mx[d] ? m : mx[d];
                sm[d] += (w0 + w1) + (w2 + w3);
            }
#pragma omp simd aligned(cf, mx2, sm2 : 64)
            for (int64_t d = 0; d < Dp; ++d) {
                const float p0 = pe0[D + d], p1 = pe1[D + d], p2 = pe2[D + d], p3 = pe3[D + d];
                const float g = cf[d];
                const float w0 = (g + p0) * p0, w1 = (g + p1) * p1;
                const float w2 = (g + p2) * p2, w3 = (g + p3) * p3;
                const float a01 = w0 > w1 ? w0 : w1, a23 = w2 > w3 ? w2 : w3;
                const float m = a01 > a23 ? a01 : a23;
                mx2[d] = m > mx2[d] ? m : mx2[d];
                sm2[d] += (w0 + w1) + (w2 + w3);
            }
        }
        for (; t < K; ++t) {
            make_pe(t, vc + t * 3, npe, cc, ax, q, fx, K, pe0);
            const float *r0 = feat + (int64_t)nr[t] * Dp;
#pragma omp simd aligned(r0, cf, pe0, mx, sm : 64)
            for (int64_t d = 0; d < Dp; ++d) {
                const float w = ((r0[d] - cf[d]) * r + pe0[d]) * pe0[d];
                mx[d] = w > mx[d] ? w : mx[d];
                sm[d] += w;
            }
#pragma omp simd aligned(cf, mx2, sm2 : 64)
            for (int64_t d = 0; d < Dp; ++d) {
                const float p = pe0[D + d];
                const float w = (cf[d] + p) * p;
                mx2[d] = w > mx2[d] ? w : mx2[d];
                sm2[d] += w;
            }
        }
        float *o = out + c * D2p;
        for (int64_t d = 0; d < D; ++d) o[d] = gelu(mx[d] + sm[d] * invk);
        for (int64_t d = 0; d < D; ++d) o[D + d] = gelu(mx2[d] + sm2[d] * invk);
        for (int64_t d = D2; d < D2p; ++d) o[d] = 0.0f;
    }
}

/* Encode one cloud. xyz: (num_points, 3); cents: concatenated Gaussian centre
 * tables (init block of init_dim/3, then 2*D_i/3 per stage); out: (feature_dim,).
 * Returns 0, or -1 when out of memory. */
#if defined(__AVX512F__)
/* Stage aggregation for 16 < D <= 32 (stage 1 of the default encoder, D = 27) with AVX-512:
 * everything for one centre stays in registers. Lanes: P = pe channels [0, 32) for the
 * offset half, Q = pe channels [D, D + 32) for the centre half. Gaussians as
 * 2^-(u s)^2 with s^2 = -q log2(e): rounding splits the exponent, a degree-5 polynomial
 * gives 2^r on [-1/2, 1/2] (PGN_EXP2_C*) and scalef applies 2^k exactly, also
 * for huge k (-> 0), so no clamping is needed.
 * ccs: (64,) pe-lane centres times s; m1, m2: (4,) lane masks axis >= 1, axis >= 2. */
static void aggregate_d32_avx512(const float *feat, int64_t D, const int64_t *cidx,
                                 const int32_t *nb, int64_t S, int64_t K, const float *vx,
                                 float r, const float *ccs, const __mmask16 *m1,
                                 const __mmask16 *m2, float s, float *out, float *acc) {
    const int64_t Dp = 32, D2p = padded(2 * D);
    const __m512 c0 = _mm512_set1_ps(PGN_EXP2_C0), c1 = _mm512_set1_ps(PGN_EXP2_C1);
    const __m512 c2 = _mm512_set1_ps(PGN_EXP2_C2), c3 = _mm512_set1_ps(PGN_EXP2_C3);
    const __m512 c4 = _mm512_set1_ps(PGN_EXP2_C4), c5 = _mm512_set1_ps(PGN_EXP2_C5);
    const __m512 vr = _mm512_set1_ps(r);
    const __m512 cc0 = _mm512_loadu_ps(ccs), cc1 = _mm512_loadu_ps(ccs + 16);
    const __m512 cc2 = _mm512_loadu_ps(ccs + 32), cc3 = _mm512_loadu_ps(ccs + 48);
    const float invk = 1.0f / (float)K;
#define PGN_PE(cc, i, dst)                                                          \
    do {                                                                            \
        __m512 va_ = _mm512_mask_blend_ps(m1[i], vb0, vb1);                         \
        va_ = _mm512_mask_blend_ps(m2[i], va_, vb2);                                \
        const __m512 u_ = _mm512_sub_ps(cc, va_);                                   \
        const __m512 t_ = _mm512_mul_ps(u_, u_);                                    \
        const __m512 k_ = _mm512_roundscale_ps(t_, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC); \
        const __m512 f_ = _mm512_sub_ps(k_, t_);  /* 2^-t = 2^f * 2^-k, |f| <= 1/2 */ \
        __m512 p_ = _mm512_fmadd_ps(c5, f_, c4);                                   \
        p_ = _mm512_fmadd_ps(p_, f_, c3);                                           \
        p_ = _mm512_fmadd_ps(p_, f_, c2);                                           \
        p_ = _mm512_fmadd_ps(p_, f_, c1);                                           \
        p_ = _mm512_fmadd_ps(p_, f_, c0);                                           \
        dst = _mm512_scalef_ps(p_, _mm512_sub_ps(_mm512_setzero_ps(), k_));         \
    } while (0)
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const __m512 cf0 = _mm512_load_ps(cf), cf1 = _mm512_load_ps(cf + 16);
        __m512 mx0 = _mm512_set1_ps(-INFINITY), mx1 = mx0, mx2 = mx0, mx3 = mx0;
        __m512 sm0 = _mm512_setzero_ps(), sm1 = sm0, sm2 = sm0, sm3 = sm0;
        const int32_t *nr = nb + c * K;
        const float *vc = vx + c * K * 3;
        for (int64_t t = 0; t < K; ++t) {
            const __m512 vb0 = _mm512_set1_ps(vc[t * 3] * s);
            const __m512 vb1 = _mm512_set1_ps(vc[t * 3 + 1] * s);
            const __m512 vb2 = _mm512_set1_ps(vc[t * 3 + 2] * s);
            __m512 p0, p1, q0, q1;
            PGN_PE(cc0, 0, p0);
            PGN_PE(cc1, 1, p1);
            PGN_PE(cc2, 2, q0);
            PGN_PE(cc3, 3, q1);
            const float *row = feat + (int64_t)nr[t] * Dp;
            const __m512 f0 = _mm512_mul_ps(_mm512_sub_ps(_mm512_load_ps(row), cf0), vr);
            const __m512 f1 = _mm512_mul_ps(_mm512_sub_ps(_mm512_load_ps(row + 16), cf1), vr);
            const __m512 w0 = _mm512_mul_ps(_mm512_add_ps(f0, p0), p0);
            const __m512 w1 = _mm512_mul_ps(_mm512_add_ps(f1, p1), p1);
            const __m512 w2 = _mm512_mul_ps(_mm512_add_ps(cf0, q0), q0);
            const __m512 w3 = _mm512_mul_ps(_mm512_add_ps(cf1, q1), q1);
            mx0 = _mm512_max_ps(mx0, w0); sm0 = _mm512_add_ps(sm0, w0);
            mx1 = _mm512_max_ps(mx1, w1); sm1 = _mm512_add_ps(sm1, w1);
            mx2 = _mm512_max_ps(mx2, w2); sm2 = _mm512_add_ps(sm2, w2);
            mx3 = _mm512_max_ps(mx3, w3); sm3 = _mm512_add_ps(sm3, w3);
        }
        const __m512 ik = _mm512_set1_ps(invk);
        _mm512_storeu_ps(acc, _mm512_fmadd_ps(sm0, ik, mx0));
        _mm512_storeu_ps(acc + 16, _mm512_fmadd_ps(sm1, ik, mx1));
        _mm512_storeu_ps(acc + 32, _mm512_fmadd_ps(sm2, ik, mx2));
        _mm512_storeu_ps(acc + 48, _mm512_fmadd_ps(sm3, ik, mx3));
        float *o = out + c * D2p;
        for (int64_t d = 0; d < D; ++d) o[d] = gelu(acc[d]);
        for (int64_t d = 0; d < D; ++d) o[D + d] = gelu(acc[32 + d]);
        for (int64_t d = 2 * D; d < D2p; ++d) o[d] = 0.0f;
    }
#undef PGN_PE
}
#endif

#if defined(__AVX512F__) && defined(__AVX512VL__)
/* Separable stages with AVX-512: pe is never stored. The 2D pe channels are walked as
 * the (axis, block) groups of 8 of the separable form, channel a n + 8 m + l, so a
 * group's pe for neighbour t is one broadcast times a vector:
 * A[t, a, m] * (T[m, 0..8) * P[t, a]^(0..8)), the powers by masked multiplies of
 * P, P^2, P^4 (the same products as sep_prepare's E, so the same values). Channel ch
 * aggregates ((row[ch] - cf[ch]) r + pe) pe for ch < D and (cf[ch - D] + pe) pe
 * above (G holds cf[ch] / cf[ch - D]); lanes past an axis's n centres are masked off.
 * mx, sm, G: 2D + 16 floats of scratch. Four neighbours a pass, like stage_aggregate. */
static inline __attribute__((always_inline)) void sep_pass(
        const float *const *rows, int nt, int64_t t0, int64_t nta, const sep_t *fx,
        int64_t D, const float *G, float r, float *mx, float *sm) {
    const int64_t n = fx->n, M = fx->M;
    const __m256 one = _mm256_set1_ps(1.0f), vr = _mm256_set1_ps(r);
    for (int a = 0; a < 3; ++a) {
        __m256 e[4];
        for (int i = 0; i < nt; ++i) {
            const int64_t ta = 3 * (t0 + i) + a;
            __m256 v = one;
            v = _mm256_mask_mul_ps(v, 0xAA, v, _mm256_set1_ps(fx->E[1 * nta + ta]));
            v = _mm256_mask_mul_ps(v, 0xCC, v, _mm256_set1_ps(fx->E[2 * nta + ta]));
            e[i] = _mm256_mask_mul_ps(v, 0xF0, v, _mm256_set1_ps(fx->E[4 * nta + ta]));
        }
        for (int64_t m = 0; m < M; ++m) {
            const int64_t ch = a * n + 8 * m;
            const int64_t nv = n - 8 * m < 8 ? n - 8 * m : 8;
            const __mmask8 valid = (__mmask8)((1u << nv) - 1u);
            const int64_t no = D - ch < 0 ? 0 : (D - ch > 8 ? 8 : D - ch);
            const __mmask8 off = (__mmask8)(((1u << no) - 1u) & valid);  /* ch + l < D */
            const __m256 T = _mm256_loadu_ps(fx->T + 8 * m);
            const __m256 g = _mm256_loadu_ps(G + ch);
            __m256 w[4];
            for (int i = 0; i < nt; ++i) {
                const __m256 am = _mm256_set1_ps(fx->A[m * nta + 3 * (t0 + i) + a]);
                const __m256 pe = _mm256_mul_ps(am, _mm256_mul_ps(T, e[i]));
                __m256 f = g;
                if (off) {
                    const __m256 row = _mm256_maskz_loadu_ps(off, rows[i] + ch);
                    f = _mm256_mask_blend_ps(off, g,
                                             _mm256_fmadd_ps(_mm256_sub_ps(row, g), vr, pe));
                    w[i] = _mm256_mul_ps(_mm256_mask_blend_ps(off, _mm256_add_ps(f, pe), f), pe);
                } else {
                    w[i] = _mm256_mul_ps(_mm256_add_ps(f, pe), pe);
                }
            }
            __m256 wm = w[0], ws = w[0];
            if (nt == 4) {
                wm = _mm256_max_ps(_mm256_max_ps(w[0], w[1]), _mm256_max_ps(w[2], w[3]));
                ws = _mm256_add_ps(_mm256_add_ps(w[0], w[1]), _mm256_add_ps(w[2], w[3]));
            }
            _mm256_mask_storeu_ps(mx + ch, valid, _mm256_max_ps(wm, _mm256_loadu_ps(mx + ch)));
            _mm256_mask_storeu_ps(sm + ch, valid, _mm256_add_ps(_mm256_loadu_ps(sm + ch), ws));
        }
    }
}

/* sep_pass with blocks of 16 (one 512-bit vector a block): P^0..15 by masked multiplies
 * of P, P^2, P^4, P^8. */
static inline __attribute__((always_inline)) void sep_pass16(
        const float *const *rows, int nt, int64_t t0, int64_t nta, const sep_t *fx,
        int64_t D, const float *G, float r, float *mx, float *sm) {
    const int64_t n = fx->n, M = fx->M;
    const __m512 one = _mm512_set1_ps(1.0f), vr = _mm512_set1_ps(r);
    for (int a = 0; a < 3; ++a) {
        __m512 e[4];
        for (int i = 0; i < nt; ++i) {
            const int64_t ta = 3 * (t0 + i) + a;
            __m512 v = one;
            v = _mm512_mask_mul_ps(v, 0xAAAA, v, _mm512_set1_ps(fx->E[1 * nta + ta]));
            v = _mm512_mask_mul_ps(v, 0xCCCC, v, _mm512_set1_ps(fx->E[2 * nta + ta]));
            v = _mm512_mask_mul_ps(v, 0xF0F0, v, _mm512_set1_ps(fx->E[4 * nta + ta]));
            e[i] = _mm512_mask_mul_ps(v, 0xFF00, v, _mm512_set1_ps(fx->E[8 * nta + ta]));
        }
        for (int64_t m = 0; m < M; ++m) {
            const int64_t ch = a * n + 16 * m;
            const int64_t nv = n - 16 * m < 16 ? n - 16 * m : 16;
            const __mmask16 valid = (__mmask16)((1u << nv) - 1u);
            const int64_t no = D - ch < 0 ? 0 : (D - ch > 16 ? 16 : D - ch);
            const __mmask16 off = (__mmask16)(((1u << no) - 1u) & valid);  /* ch + l < D */
            const __m512 T = _mm512_loadu_ps(fx->T + 16 * m);
            const __m512 g = _mm512_loadu_ps(G + ch);
            __m512 w[4];
            for (int i = 0; i < nt; ++i) {
                const __m512 am = _mm512_set1_ps(fx->A[m * nta + 3 * (t0 + i) + a]);
                const __m512 pe = _mm512_mul_ps(am, _mm512_mul_ps(T, e[i]));
                if (off) {
                    const __m512 row = _mm512_maskz_loadu_ps(off, rows[i] + ch);
                    const __m512 f = _mm512_mask_blend_ps(
                        off, g, _mm512_fmadd_ps(_mm512_sub_ps(row, g), vr, pe));
                    w[i] = _mm512_mul_ps(_mm512_mask_blend_ps(off, _mm512_add_ps(f, pe), f), pe);
                } else {
                    w[i] = _mm512_mul_ps(_mm512_add_ps(g, pe), pe);
                }
            }
            __m512 wm = w[0], ws = w[0];
            if (nt == 4) {
                wm = _mm512_max_ps(_mm512_max_ps(w[0], w[1]), _mm512_max_ps(w[2], w[3]));
                ws = _mm512_add_ps(_mm512_add_ps(w[0], w[1]), _mm512_add_ps(w[2], w[3]));
            }
            _mm512_mask_storeu_ps(mx + ch, valid, _mm512_max_ps(wm, _mm512_loadu_ps(mx + ch)));
            _mm512_mask_storeu_ps(sm + ch, valid, _mm512_add_ps(_mm512_loadu_ps(sm + ch), ws));
        }
    }
}

static void aggregate_sep_avx512(const float *feat, int64_t D, const int64_t *cidx,
                                 const int32_t *nb, int64_t S, int64_t K, const float *vx,
                                 float r, float *out, float *mx, float *sm, float *G,
                                 sep_t *fx) {
    const int64_t Dp = padded(D), D2 = 2 * D, D2p = padded(D2), nta = 3 * K;
    const float invk = 1.0f / (float)K;
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const int32_t *nr = nb + c * K;
        for (int64_t d = 0; d < D; ++d) { G[d] = cf[d]; G[D + d] = cf[d]; }
        for (int64_t d = D2; d < D2 + 32; ++d) G[d] = 0.0f;
        for (int64_t d = 0; d < D2 + 32; ++d) { mx[d] = -INFINITY; sm[d] = 0.0f; }
        sep_prepare(fx, vx + c * K * 3, K);
        int64_t t = 0;
        for (; t + 4 <= K; t += 4) {
            const float *rows[4] = {feat + (int64_t)nr[t] * Dp, feat + (int64_t)nr[t + 1] * Dp,
                                    feat + (int64_t)nr[t + 2] * Dp, feat + (int64_t)nr[t + 3] * Dp};
            if (fx->B == 16) sep_pass16(rows, 4, t, nta, fx, D, G, r, mx, sm);
            else sep_pass(rows, 4, t, nta, fx, D, G, r, mx, sm);
        }
        for (; t < K; ++t) {
            const float *rows[1] = {feat + (int64_t)nr[t] * Dp};
            if (fx->B == 16) sep_pass16(rows, 1, t, nta, fx, D, G, r, mx, sm);
            else sep_pass(rows, 1, t, nta, fx, D, G, r, mx, sm);
        }
        float *o = out + c * D2p;
        for (int64_t d = 0; d < D2; ++d) o[d] = gelu(mx[d] + sm[d] * invk);
        for (int64_t d = D2; d < D2p; ++d) o[d] = 0.0f;
    }
}
#endif

#if defined(__AVX512F__)
/* Sums of e = row[d] - cf[d] and e^2 over one centre's K neighbour rows, channels
 * [0, Dp), with the per-channel partials in registers: chunks of up to 4 vectors, two
 * sets of accumulators (even / odd neighbours) so the add chains overlap. */
#define PGN_STDCHUNK(NV)                                                                 \
    static inline void stdchunk##NV(const float *feat, int64_t Dp, const int32_t *nr,    \
                                    int64_t K, const float *cf, __m512 *t1, __m512 *t2) { \
        __m512 a1[2][NV], a2[2][NV], g[NV];                                              \
        for (int v = 0; v < NV; ++v) {                                                   \
            g[v] = _mm512_load_ps(cf + 16 * v);                                          \
            a1[0][v] = a1[1][v] = a2[0][v] = a2[1][v] = _mm512_setzero_ps();             \
        }                                                                                \
        int64_t t = 0;                                                                   \
        for (; t + 2 <= K; t += 2) {                                                     \
            const float *r0 = feat + (int64_t)nr[t] * Dp;                                \
            const float *r1 = feat + (int64_t)nr[t + 1] * Dp;                            \
            for (int v = 0; v < NV; ++v) {                                               \
                const __m512 e0 = _mm512_sub_ps(_mm512_load_ps(r0 + 16 * v), g[v]);      \
                const __m512 e1 = _mm512_sub_ps(_mm512_load_ps(r1 + 16 * v), g[v]);      \
                a1[0][v] = _mm512_add_ps(a1[0][v], e0);                                  \
                a2[0][v] = _mm512_fmadd_ps(e0, e0, a2[0][v]);                            \
                a1[1][v] = _mm512_add_ps(a1[1][v], e1);                                  \
                a2[1][v] = _mm512_fmadd_ps(e1, e1, a2[1][v]);                            \
            }                                                                            \
        }                                                                                \
        if (t < K) {                                                                     \
            const float *r0 = feat + (int64_t)nr[t] * Dp;                                \
            for (int v = 0; v < NV; ++v) {                                               \
                const __m512 e0 = _mm512_sub_ps(_mm512_load_ps(r0 + 16 * v), g[v]);      \
                a1[0][v] = _mm512_add_ps(a1[0][v], e0);                                  \
                a2[0][v] = _mm512_fmadd_ps(e0, e0, a2[0][v]);                            \
            }                                                                            \
        }                                                                                \
        for (int v = 0; v < NV; ++v) {                                                   \
            *t1 = _mm512_add_ps(*t1, _mm512_add_ps(a1[0][v], a1[1][v]));                 \
            *t2 = _mm512_add_ps(*t2, _mm512_add_ps(a2[0][v], a2[1][v]));                 \
        }                                                                                \
    }
PGN_STDCHUNK(1)
PGN_STDCHUNK(2)
PGN_STDCHUNK(3)
PGN_STDCHUNK(4)
#undef PGN_STDCHUNK

static void std_centre_avx512(const float *feat, int64_t Dp, const int32_t *nr, int64_t K,
                              const float *cf, float *a1, float *a2) {
    __m512 t1 = _mm512_setzero_ps(), t2 = t1;
    int64_t v = 0;
    const int64_t nv = Dp / 16;
    for (; v + 4 <= nv; v += 4) stdchunk4(feat + 16 * v, Dp, nr, K, cf + 16 * v, &t1, &t2);
    switch (nv - v) {
        case 3: stdchunk3(feat + 16 * v, Dp, nr, K, cf + 16 * v, &t1, &t2); break;
        case 2: stdchunk2(feat + 16 * v, Dp, nr, K, cf + 16 * v, &t1, &t2); break;
        case 1: stdchunk1(feat + 16 * v, Dp, nr, K, cf + 16 * v, &t1, &t2); break;
        default: break;
    }
    *a1 = _mm512_reduce_add_ps(t1);
    *a2 = _mm512_reduce_add_ps(t2);
}
#endif

/* Whether separable Gaussians are safe in float for n centres in (-1, 1) and this q
 * (see sep_t), and worth it (n >= SEP_MIN_N). */
static int sep_ok(int64_t n, double q, int B) {
    const double aq = fabs(q), h = 2.0 / (double)(n + 1), W = 1.0 + sqrt(87.0 / aq);
    const double L = (double)(B - 1);  /* largest power of P in a block */
    return n >= SEP_MIN_N && 2.0 * L * aq * h * (1.0 + W) + L * L * aq * h * h < 80.0
           && L * h * sqrt(aq) < 3.8;
}

/* A lone cloud on two threads: the caller and one helper share each stage's
 * aggregation by chunks of centres, claimed from an atomic counter. Every centre's
 * result depends on that centre only, so the split never changes a bit. The caller
 * works through the chunks itself and waits only for chunks the helper has claimed:
 * a helper that is not scheduled in time costs nothing but its wake-up. */
typedef struct agg_job {
    const float *feat;
    int64_t D, S, K, D2p, PS, nchunks;
    const int64_t *cidx;
    const int32_t *nb;
    const float *vx, *cc;
    const int32_t *ax;
    float r, q;
    float *out;
    sep_t fx[2];          /* per thread: its own A / E scratch */
    int use_fx, d32;
    float *pe[2], *mx[2], *sm[2];
#if defined(__AVX512F__)
    const float *ccs;
    const __mmask16 *m1, *m2;
    float sc;
#endif
} agg_job;

static void agg_chunk(agg_job *j, int tid, int64_t chunk) {
    const int64_t c0 = j->S * chunk / j->nchunks, c1 = j->S * (chunk + 1) / j->nchunks;
    if (c1 <= c0) return;
    const int64_t *cidx = j->cidx + c0;
    const int32_t *nb = j->nb + c0 * j->K;
    const float *vx = j->vx + c0 * j->K * 3;
    float *out = j->out + c0 * j->D2p;
#if defined(__AVX512F__) && !defined(PGN_NO_D32)
    if (j->d32) {
        aggregate_d32_avx512(j->feat, j->D, cidx, nb, c1 - c0, j->K, vx, j->r, j->ccs, j->m1,
                             j->m2, j->sc, out, j->mx[tid]);
        return;
    }
#endif
#if defined(__AVX512F__) && defined(__AVX512VL__) && !defined(PGN_NO_SEP512)
    if (j->use_fx) {
        aggregate_sep_avx512(j->feat, j->D, cidx, nb, c1 - c0, j->K, vx, j->r, out, j->mx[tid],
                             j->sm[tid], j->pe[tid], &j->fx[tid]);
        return;
    }
#endif
    stage_aggregate(j->feat, j->D, cidx, nb, c1 - c0, j->K, vx, j->r, j->cc, j->ax, j->q, out,
                    j->pe[tid], j->PS, j->mx[tid], j->sm[tid], j->use_fx ? &j->fx[tid] : NULL);
}

typedef struct {
    pthread_mutex_t mu;
    pthread_cond_t cv;
    int64_t gen;          /* job generation, under mu */
    int quit;
    agg_job *job;
    _Atomic uint64_t next;  /* (generation << 32) | next unclaimed chunk */
    _Atomic int64_t done;   /* chunks of the current job finished */
} par_t;

/* Claim and run chunks of job generation gen until none is left. */
static void par_work(par_t *p, agg_job *job, uint64_t gen, int tid) {
    for (;;) {
        uint64_t v = atomic_load(&p->next);
        if ((v >> 32) != gen || (int64_t)(v & 0xffffffffu) >= job->nchunks) return;
        if (!atomic_compare_exchange_weak(&p->next, &v, v + 1)) continue;
        agg_chunk(job, tid, (int64_t)(v & 0xffffffffu));
        atomic_fetch_add(&p->done, 1);
    }
}

static void *par_helper(void *arg) {
    par_t *p = arg;
    int64_t seen = 0;
    pthread_mutex_lock(&p->mu);
    for (;;) {
        while (p->gen == seen && !p->quit) pthread_cond_wait(&p->cv, &p->mu);
        if (p->quit) break;
        seen = p->gen;
        agg_job *job = p->job;
        pthread_mutex_unlock(&p->mu);
        par_work(p, job, (uint64_t)seen, 1);
        pthread_mutex_lock(&p->mu);
    }
    pthread_mutex_unlock(&p->mu);
    return NULL;
}

/* Run all chunks of job, with the helper when there is one. */
static void par_run(par_t *p, agg_job *job) {
    if (!p) {
        for (int64_t i = 0; i < job->nchunks; ++i) agg_chunk(job, 0, i);
        return;
    }
    pthread_mutex_lock(&p->mu);
    const uint64_t gen = (uint64_t)++p->gen;
    p->job = job;
    atomic_store(&p->done, 0);
    atomic_store(&p->next, gen << 32);
    pthread_cond_signal(&p->cv);
    pthread_mutex_unlock(&p->mu);
    par_work(p, job, gen, 0);
    for (int spin = 0; atomic_load(&p->done) < job->nchunks; ++spin)
        if (spin > 64) sched_yield();  /* only chunks the helper is running are left */
}

static int encode_one(const float *xyz_in, const pgn_cfg *cfg, const float *cents, float *out,
                      par_t *par) {
    TIC(11);
    const int64_t N = cfg->num_points, D0 = cfg->init_dim;
    const float q = -0.5f / (cfg->sigma * cfg->sigma);
    const int64_t S1 = N / 2;
    const int64_t K1 = cfg->k < N ? cfg->k : N;
    const int64_t Dmax = D0 << cfg->stages;  /* widest 2D */
    /* Every stage holds S_i rows of padded(2 D_i) <= N * D0 + S_i * PAD features. */
    const int64_t fsz = N * (D0 + PAD);
    float *featA = xalloc(sizeof(float) * (size_t)fsz);
    float *featB = xalloc(sizeof(float) * (size_t)fsz);
    float *xyz = xalloc(sizeof(float) * (size_t)N * 3);
    float *cxyz = xalloc(sizeof(float) * (size_t)N * 3);
    float *soa = xalloc(sizeof(float) * (size_t)N * 6);
    float *scratch = xalloc(sizeof(float) * (size_t)N);
    float *vx = xalloc(sizeof(float) * (size_t)S1 * K1 * 3);
    /* one scratch vector / pe buffer: a multiple of 64 bytes, since the vector loops
     * declare their pointers 64-byte aligned */
    const int64_t VS = padded(Dmax + 4 * PAD), PS = VS;
    float *vec = xalloc(sizeof(float) * (size_t)VS * 3);
    float *pe = xalloc(sizeof(float) * (size_t)PS * 4);
    int32_t *ax = xalloc(sizeof(int32_t) * (size_t)VS);
    int64_t *cidx = xalloc(sizeof(int64_t) * (size_t)S1);
    const int64_t Mmax = (Dmax / 3 + 7) / 8;
    float *sepb = xalloc(sizeof(float) * (size_t)Mmax);
    float *sepT = xalloc(sizeof(float) * (size_t)(Mmax + 1) * 16);
    float *sepA = xalloc(sizeof(float) * (size_t)K1 * 3 * Mmax);
    float *sepE = xalloc(sizeof(float) * (size_t)K1 * 3 * 9);  /* rows 0..8 of E */
    /* the helper's own scratch (pe buffers, mx / sm, separable A / E) */
    const int npar = par ? 2 : 1;
    float *pe2 = par ? xalloc(sizeof(float) * (size_t)PS * 4) : NULL;
    float *vec2 = par ? xalloc(sizeof(float) * (size_t)VS * 2) : NULL;
    float *sepA2 = par ? xalloc(sizeof(float) * (size_t)K1 * 3 * Mmax) : NULL;
    float *sepE2 = par ? xalloc(sizeof(float) * (size_t)K1 * 3 * 9) : NULL;
    int32_t *nb = xalloc(sizeof(int32_t) * (size_t)(S1 * K1 + 16));
    uint64_t *keys = xalloc(sizeof(uint64_t) * (size_t)(2 * N + 32));
    int rc = 0;
    TOC(11, 11);
    if (!featA || !featB || !xyz || !cxyz || !soa || !scratch || !vx || !vec || !ax || !cidx
        || !nb || !keys || !pe || !sepb || !sepT || !sepA || !sepE
        || (npar == 2 && (!pe2 || !vec2 || !sepA2 || !sepE2))) {
        rc = -1;
        goto done;
    }
    float *cc = vec, *mx = vec + VS, *sm = vec + 2 * VS;
    memcpy(xyz, xyz_in, sizeof(float) * (size_t)N * 3);
    /* initial embedding: (N, padded(D0)) */
    TIC(8);
    {
        const int64_t n0 = D0 / 3, D0p = padded(D0);
        for (int64_t i = 0; i < N; ++i) gpe3(xyz + i * 3, cents, n0, q, featA + i * D0p);
        cents += n0;
    }
    TOC(8, 8);
    float *feat = featA, *nfeat = featB;
    int64_t n = N, D = D0;
    float *o = out;
    for (int64_t st = 0; st < cfg->stages; ++st) {
        const int64_t S = n / 2, K = cfg->k < n ? cfg->k : n, D2 = 2 * D, nc = D2 / 3;
        const int64_t Dp = padded(D), D2p = padded(D2);
        float *x = soa, *y = soa + n, *z = soa + 2 * n;
        for (int64_t i = 0; i < n; ++i) { x[i] = xyz[i * 3]; y[i] = xyz[i * 3 + 1]; z[i] = xyz[i * 3 + 2]; }
        TIC(1);
        pgn_fps(xyz, x, y, z, n, S, cidx, scratch);
        TOC(1, 0);
        float *cx = soa + 3 * n, *cy = cx + S, *cz = cy + S;
        for (int64_t c = 0; c < S; ++c) {
            cx[c] = x[cidx[c]]; cy[c] = y[cidx[c]]; cz[c] = z[cidx[c]];
            cxyz[c * 3] = cx[c]; cxyz[c * 3 + 1] = cy[c]; cxyz[c * 3 + 2] = cz[c];
        }
        TIC(2);
        pgn_knn(x, y, z, n, cx, cy, cz, S, K, nb, scratch, keys);
        TOC(2, 1);
        TIC(3);
        /* offsets (gathered rows of the AoS copy: no running sums, so no dependency
         * chain per neighbour), then their unbiased std by two vectorised passes: float
         * blocks, double totals */
        double s1 = 0.0, s2 = 0.0;
        for (int64_t c = 0; c < S; ++c) {
            const float qx = cx[c], qy = cy[c], qz = cz[c];
            const int32_t *nr = nb + c * K;
            float *v = vx + c * K * 3;
            for (int64_t t = 0; t < K; ++t) {
                const float *pj = xyz + (int64_t)nr[t] * 3;
                v[t * 3] = pj[0] - qx; v[t * 3 + 1] = pj[1] - qy; v[t * 3 + 2] = pj[2] - qz;
            }
        }
        const int64_t nv = S * K * 3;
        for (int64_t i = 0; i < nv; i += 4096) {
            const int64_t e = i + 4096 < nv ? i + 4096 : nv;
            float acc = 0.0f;
#pragma omp simd reduction(+:acc)
            for (int64_t u = i; u < e; ++u) acc += vx[u];
            s1 += acc;
        }
        const float mvf = (float)(s1 / (double)nv);
        for (int64_t i = 0; i < nv; i += 4096) {
            const int64_t e = i + 4096 < nv ? i + 4096 : nv;
            float acc = 0.0f;
#pragma omp simd reduction(+:acc)
            for (int64_t u = i; u < e; ++u) { const float d = vx[u] - mvf; acc += d * d; }
            s2 += acc;
        }
        const float rx = (float)(1.0 / (sqrt(s2 / (double)(nv - 1)) + 1e-5));
#pragma omp simd
        for (int64_t i = 0; i < nv; ++i) vx[i] *= rx;
        TOC(3, 10);
        TIC(7);
        /* std of feature offsets: per-channel float partials over a centre's neighbours
         * (4 rows a pass, no horizontal sum per row), reduced once per centre into
         * double totals */
        double f1 = 0.0, f2 = 0.0;
        {
            float *s1 = mx, *s2 = sm;
            for (int64_t c = 0; c < S; ++c) {
                const float *cf = feat + cidx[c] * Dp;
                const int32_t *nr = nb + c * K;
#if defined(__AVX512F__)
                {
                    float a1, a2;
                    std_centre_avx512(feat, Dp, nr, K, cf, &a1, &a2);
                    f1 += a1; f2 += a2;
                    continue;
                }
#endif
                for (int64_t d = 0; d < Dp; ++d) { s1[d] = 0.0f; s2[d] = 0.0f; }
                int64_t t = 0;
                for (; t + 4 <= K; t += 4) {
                    const float *r0 = feat + (int64_t)nr[t] * Dp, *r1 = feat + (int64_t)nr[t + 1] * Dp;
                    const float *r2 = feat + (int64_t)nr[t + 2] * Dp, *r3 = feat + (int64_t)nr[t + 3] * Dp;
#pragma omp simd aligned(r0, r1, r2, r3, cf, s1, s2 : 64)
                    for (int64_t d = 0; d < Dp; ++d) {
                        const float e0 = r0[d] - cf[d], e1 = r1[d] - cf[d];
                        const float e2 = r2[d] - cf[d], e3 = r3[d] - cf[d];
                        s1[d] += (e0 + e1) + (e2 + e3);
                        s2[d] += (e0 * e0 + e1 * e1) + (e2 * e2 + e3 * e3);
                    }
                }
                for (; t < K; ++t) {
                    const float *r0 = feat + (int64_t)nr[t] * Dp;
#pragma omp simd aligned(r0, cf, s1, s2 : 64)
                    for (int64_t d = 0; d < Dp; ++d) {
                        const float e0 = r0[d] - cf[d];
                        s1[d] += e0;
                        s2[d] += e0 * e0;
                    }
                }
                float a1 = 0.0f, a2 = 0.0f;
#pragma omp simd reduction(+:a1, a2) aligned(s1, s2 : 64)
                for (int64_t d = 0; d < Dp; ++d) { a1 += s1[d]; a2 += s2[d]; }
                f1 += a1; f2 += a2;
            }
        }
        const double nf = (double)(S * K * D);
        double var = (f2 - f1 * f1 / nf) / (nf - 1.0);
        if (var < 0.0) var = 0.0;
        const float rf = (float)(1.0 / (sqrt(var) + 1e-5));
        TOC(7, 7);
        TIC(4);
        /* per-channel centre and axis of the pe channels (padding lanes: ignored) */
        for (int64_t d = 0; d < VS; ++d) { cc[d] = 0.0f; ax[d] = 0; }
        for (int64_t d = 0; d < D2; ++d) { cc[d] = cents[d % nc]; ax[d] = (int32_t)(d / nc); }
        sep_t fxs, *fx = NULL;
        /* blocks of 16 where the AVX-512 path runs and float range allows, else of 8 */
        int B = 0;
#if defined(__AVX512F__) && defined(__AVX512VL__) && !defined(PGN_NO_SEP512)
        if (sep_ok(nc, (double)q, 16)) B = 16;
#endif
        if (!B && sep_ok(nc, (double)q, 8)) B = 8;
        if (B) {
            /* grid from the exact linspace formula, in double, rounded once */
            const double h = 2.0 / (double)(nc + 1), b0 = -1.0 + h, qd = (double)q;
            fxs.n = nc;
            fxs.B = B;
            fxs.M = (nc + B - 1) / B;
            fxs.q = q;
            fxs.h2q = (float)(-2.0 * qd * h);
            fxs.W = (float)(1.0 + sqrt(87.0 / fabs(qd)));
            for (int64_t m = 0; m < fxs.M; ++m) {
                const double bm = b0 + (double)B * (double)m * h;
                sepb[m] = (float)bm;
                for (int l = 0; l < B; ++l)
                    sepT[m * B + l] = (float)exp(2.0 * qd * l * h * bm + qd * l * l * h * h);
            }
            fxs.b = sepb;
            fxs.T = sepT;
            fxs.A = sepA;
            fxs.E = sepE;
            fx = &fxs;
        }
        agg_job job;
        memset(&job, 0, sizeof(job));
        job.feat = feat; job.D = D; job.S = S; job.K = K; job.D2p = D2p; job.PS = PS;
        job.cidx = cidx; job.nb = nb; job.vx = vx; job.cc = cc; job.ax = ax; job.r = rf;
        job.q = q; job.out = nfeat;
        /* 16 chunks on two threads: a claimed chunk is short, so the caller never waits
         * long for a helper that was descheduled mid-chunk */
        job.nchunks = par ? (S < 16 ? S : 16) : 1;
        job.pe[0] = pe; job.mx[0] = mx; job.sm[0] = sm;
        job.pe[1] = pe2; job.mx[1] = vec2; job.sm[1] = vec2 ? vec2 + VS : NULL;
        if (fx) {
            job.use_fx = 1;
            job.fx[0] = *fx;
            job.fx[1] = *fx;
            job.fx[1].A = sepA2;
            job.fx[1].E = sepE2;
        }
#if defined(__AVX512F__) && !defined(PGN_NO_D32)
        const float sc = sqrtf(-q * 1.44269504088896341f);
        float ccs[64];
        __mmask16 m1[4] = {0}, m2[4] = {0};
        if (!fx && D > 16 && D <= 32) {
            /* register-resident path; pe lanes: channels [0, 32) and [D, D + 32) */
            for (int i = 0; i < 64; ++i) {
                const int64_t ch = i < 32 ? i : D + (i - 32);
                const int axis = ch < D2 ? (int)(ch / nc) : 0;
                ccs[i] = ch < D2 ? cents[ch % nc] * sc : 0.0f;
                if (axis >= 1) m1[i / 16] |= (__mmask16)(1u << (i % 16));
                if (axis >= 2) m2[i / 16] |= (__mmask16)(1u << (i % 16));
            }
            job.d32 = 1;
            job.ccs = ccs; job.m1 = m1; job.m2 = m2; job.sc = sc;
        }
#endif
        par_run(par, &job);
        TOC(4, 3 + st);
        TIC(9);
        cents += nc;
        /* global max and mean over centres */
        for (int64_t d = 0; d < D2; ++d) { o[d] = -INFINITY; o[D2 + d] = 0.0f; }
        for (int64_t c = 0; c < S; ++c) {
            const float *rr = nfeat + c * D2p;
            for (int64_t d = 0; d < D2; ++d) { o[d] = rr[d] > o[d] ? rr[d] : o[d]; o[D2 + d] += rr[d]; }
        }
        for (int64_t d = 0; d < D2; ++d) o[D2 + d] /= (float)S;
        o += 2 * D2;
        TOC(9, 9);
        float *tmp = feat; feat = nfeat; nfeat = tmp;
        memcpy(xyz, cxyz, sizeof(float) * (size_t)S * 3);
        n = S;
        D = D2;
    }
done:
    free(featA); free(featB); free(xyz); free(cxyz); free(soa); free(scratch); free(vx);
    free(vec); free(pe); free(ax); free(cidx); free(nb); free(keys);
    free(sepb); free(sepT); free(sepA); free(sepE);
    free(pe2); free(vec2); free(sepA2); free(sepE2);
    return rc;
}

/* Encode clouds [0, count): xyz (count, num_points, 3) -> out (count, feature_dim). */
int pgn_encode(const float *xyz, int64_t count, int64_t num_points, int64_t init_dim,
               int64_t stages, int64_t k, float sigma, const float *cents, int64_t feature_dim,
               float *out) {
    pgn_cfg cfg = {num_points, init_dim, stages, k, sigma};
    for (int64_t b = 0; b < count; ++b) {
        int rc = encode_one(xyz + b * num_points * 3, &cfg, cents, out + b * feature_dim, NULL);
        if (rc) return rc;
    }
    return 0;
}

/* One cloud on the calling thread plus a helper thread (started and joined here: ~50 us)
 * that shares the aggregation; bit-identical to pgn_encode. Falls back to one thread
 * when the helper cannot start. Returns 0, or -1 when out of memory. */
int pgn_encode_lone(const float *xyz, int64_t num_points, int64_t init_dim, int64_t stages,
                    int64_t k, float sigma, const float *cents, int64_t feature_dim, float *out) {
    (void)feature_dim;
    pgn_cfg cfg = {num_points, init_dim, stages, k, sigma};
    par_t p;
    memset(&p, 0, sizeof(p));
    pthread_mutex_init(&p.mu, NULL);
    pthread_cond_init(&p.cv, NULL);
    atomic_init(&p.next, 0);
    atomic_init(&p.done, 0);
    pthread_t th;
    const int started = pthread_create(&th, NULL, par_helper, &p) == 0;
    const int rc = encode_one(xyz, &cfg, cents, out, started ? &p : NULL);
    if (started) {
        pthread_mutex_lock(&p.mu);
        p.quit = 1;
        pthread_cond_signal(&p.cv);
        pthread_mutex_unlock(&p.mu);
        pthread_join(th, NULL);
    }
    pthread_cond_destroy(&p.cv);
    pthread_mutex_destroy(&p.mu);
    return rc;
}
