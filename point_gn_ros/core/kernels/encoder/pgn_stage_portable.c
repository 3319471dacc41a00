/* Point-GN stage kernels, portable C: separable-Gaussian factors (pgn_sep_prepare), the
 * generic neighbourhood aggregation (pgn_stage_aggregate); the separable form's plan is in
 * pgn_stage_plan.c.
 *
 * The ISA versions are in pgn_avx512*.c and pgn_avx2*.c (pgn_dispatch.c's table);
 * pgn_encode.c drives one cloud through the stages.
 */
#include "pgn_common.h"

/* exp(x) for x in [-87, 87] (callers clamp): Cody-Waite range reduction and a
 * degree-6 polynomial, relative error < 2e-7. Inline and branch-free, so the
 * pe loop vectorises without library calls or special-case lanes. */
static inline float exp_fast(float x) {
    /* k by a truncating conversion of t +- 1/2 (roundf's value but where t + 1/2 rounds up
     * to the next integer, which the reduction absorbs): it vectorises on plain SSE2, where
     * roundf has no vector instruction and would keep the loops scalar */
    const float t = x * 1.44269504088896341f;
    const int32_t ki = (int32_t)(t + __builtin_copysignf(0.5f, t));
    const float kf = (float)ki;
    float r = x - kf * 0.693145751953125f;
    r = r - kf * 1.428606765330187e-06f;
    float p = 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    const int32_t bits = (ki + 127) << 23;
    float scale;
    memcpy(&scale, &bits, 4);
    return p * scale;
}

/* A and E for one centre's K neighbours, v (K, 3) normalised offsets; stored
 * neighbour-axis minor (A[m][ta], E[l][ta], ta = 3 t + a) so every loop here runs
 * vectorised across the 3 K (t, a) pairs. */
void pgn_sep_prepare(sep_t *fx, const float *v, int64_t K) {
    const int64_t M = fx->M, nta = K * 3;
    float *w = fx->E;  /* row 0 of E (all ones) is filled last: use it for w meanwhile */
    const float W = fx->W;
#if defined(__AVX512F__)
    if (fx->C) {  /* AVX-512 chains only blocks of 16 (pgn_sep_plan) */
        /* AVX-512's stages 2-4 in one pass: the clamp, A_0 and P^16 by exponentials, then
         * A_{m+1} = A_m (P^16 C_m) (sep_t: the factor off the chain, so a step waits for
         * one multiply), and P, P^2, P^4, P^8 for sep_centre16 (P by the same 2^-t) */
        const float l2e = 1.44269504088896341f;
        const __m512 vb = _mm512_set1_ps(fx->b[0]), vs = _mm512_set1_ps(-fx->q * l2e);
        const __m512 s16 = _mm512_set1_ps(-16.0f * fx->h2q * l2e);
        const __m512 s1 = _mm512_set1_ps(-fx->h2q * l2e);
        const __m512 vW = _mm512_set1_ps(W), vnW = _mm512_set1_ps(-W);
        const float *restrict C = fx->C;
        float *restrict A = fx->A, *restrict E = fx->E;
        for (int64_t i = 0; i < nta; i += 16) {
            const __mmask16 k = nta - i >= 16 ? (__mmask16)0xffff
                                              : (__mmask16)((1u << (nta - i)) - 1u);
            const __m512 wv = _mm512_min_ps(_mm512_max_ps(_mm512_maskz_loadu_ps(k, v + i),
                                                          vnW), vW);
            const __m512 u = _mm512_sub_ps(vb, wv);
            __m512 a = exp2_neg_avx512(_mm512_mul_ps(_mm512_mul_ps(u, u), vs));
            const __m512 p16 = exp2_neg_avx512(_mm512_mul_ps(s16, wv));
            const __m512 p1 = exp2_neg_avx512(_mm512_mul_ps(s1, wv));
            const __m512 p2 = _mm512_mul_ps(p1, p1), p4 = _mm512_mul_ps(p2, p2);
            _mm512_mask_storeu_ps(E + nta + i, k, p1);
            _mm512_mask_storeu_ps(E + 2 * nta + i, k, p2);
            _mm512_mask_storeu_ps(E + 4 * nta + i, k, p4);
            _mm512_mask_storeu_ps(E + 8 * nta + i, k, _mm512_mul_ps(p4, p4));
            _mm512_mask_storeu_ps(A + i, k, a);
            for (int64_t m = 1; m < M; ++m) {
                a = _mm512_mul_ps(a, _mm512_mul_ps(p16, _mm512_set1_ps(C[m - 1])));
                _mm512_mask_storeu_ps(A + m * nta + i, k, a);
            }
        }
        return;
    }
#endif
#pragma omp simd
    for (int64_t i = 0; i < nta; ++i) w[i] = v[i] < -W ? -W : (v[i] > W ? W : v[i]);
#if defined(PGN_AVX2)
    if (fx->C) {  /* as above with blocks of 8: A_{m+1} = A_m P^8 C_m */
        const __m256 vb = _mm256_set1_ps(fx->b[0]);
        const __m256 vs = _mm256_set1_ps(-fx->q * 1.44269504088896341f);
        const __m256 s8 = _mm256_set1_ps(-8.0f * fx->h2q * 1.44269504088896341f);
        const __m256 tmax = _mm256_set1_ps(125.0f);
        for (int64_t i = 0; i < nta; i += 8) {
            /* the last few through a zero-padded copy, their results back one by one */
            const int64_t nl = nta - i < 8 ? nta - i : 8;
            float tw[8] = {0}, ta[8];
            if (nl < 8)
                for (int64_t l = 0; l < nl; ++l) tw[l] = w[i + l];
            const __m256 wv = _mm256_loadu_ps(nl == 8 ? w + i : tw);
            const __m256 u = _mm256_sub_ps(vb, wv);
            const __m256 t = _mm256_mul_ps(_mm256_mul_ps(u, u), vs);
            /* exp2_neg_avx2 clamps t at 125 (2^-125, not 0): a chain must start from 0 */
            __m256 a = _mm256_and_ps(exp2_neg_avx2(t), _mm256_cmp_ps(t, tmax, _CMP_LT_OQ));
            const __m256 p8 = exp2_neg_avx2(_mm256_mul_ps(s8, wv));
            for (int64_t m = 0; m < M; ++m) {
                if (m) a = _mm256_mul_ps(_mm256_mul_ps(a, p8), _mm256_set1_ps(fx->C[m - 1]));
                if (nl == 8) {
                    _mm256_storeu_ps(fx->A + m * nta + i, a);
                } else {
                    _mm256_storeu_ps(ta, a);
                    for (int64_t l = 0; l < nl; ++l) fx->A[m * nta + i + l] = ta[l];
                }
            }
        }
    }
#endif
    for (int64_t m = 0; m < M && !fx->C; ++m) {
        const float bm = fx->b[m], q = fx->q;
        float *A = fx->A + m * nta;
#if defined(__AVX512F__)
        /* 16 lanes: 2^-(u^2 |q| log2 e) by rounding + polynomial + scalef (as in
         * pgn_aggregate_narrow_avx512), the exponent clamped like exp_fast's -87 */
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
#elif defined(PGN_AVX2)
        /* 8 lanes: the same 2^-t (exp2_neg_avx2 clamps t at 125, about 87 log2 e) */
        const __m256 vb = _mm256_set1_ps(bm), vs = _mm256_set1_ps(-q * 1.44269504088896341f);
        int64_t i = 0;
        for (; i + 8 <= nta; i += 8) {
            const __m256 u = _mm256_sub_ps(vb, _mm256_loadu_ps(w + i));
            _mm256_storeu_ps(A + i, exp2_neg_avx2(_mm256_mul_ps(_mm256_mul_ps(u, u), vs)));
        }
        if (i < nta) {  /* tail through a padded copy */
            float tw[8] = {0}, ta[8];
            for (int64_t l = i; l < nta; ++l) tw[l - i] = w[l];
            const __m256 u = _mm256_sub_ps(vb, _mm256_loadu_ps(tw));
            _mm256_storeu_ps(ta, exp2_neg_avx2(_mm256_mul_ps(_mm256_mul_ps(u, u), vs)));
            for (int64_t l = i; l < nta; ++l) A[l] = ta[l - i];
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
    if (fx->B == 16) {  /* P, P^2, P^4, P^8: sep_centre16 builds the 16 powers */
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
void pgn_stage_aggregate(const float *feat, int64_t D, const int64_t *cidx, const int32_t *nb,
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
        if (fx) pgn_sep_prepare(fx, vc, K);
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
        for (int64_t d = 0; d < D; ++d) o[d] = mx[d] + sm[d] * invk;
        for (int64_t d = 0; d < D; ++d) o[D + d] = mx2[d] + sm2[d] * invk;
        for (int64_t d = D2; d < D2p; ++d) o[d] = 0.0f;
    }
}
