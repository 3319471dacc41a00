/* Point-GN stage kernels with AVX-512 intrinsics (only where the compiler targets
 * AVX-512; elsewhere this file is empty and pgn_encode.c uses the portable kernels): stage
 * 1's channels-in-lanes kernel and the std pass. The separable stages: pgn_avx512_separable.c. */
#include "pgn_common.h"

#if defined(__AVX512F__)
/* Stage aggregation for 16 < D <= 32 (stage 1 of the default encoder, D = 27) with AVX-512:
 * everything for one centre stays in registers. Lanes: P = pe channels [0, 32) for the
 * offset half, Q = pe channels [D, D + 32) for the centre half. Gaussians as
 * 2^-(u s)^2 with s^2 = -q log2(e): rounding splits the exponent, a degree-5 polynomial
 * gives 2^r on [-1/2, 1/2] (PGN_EXP2_C*) and scalef applies 2^k exactly, also
 * for huge k (-> 0), so no clamping is needed.
 * ccs: (64,) pe-lane centres times s; m1, m2: (4,) lane masks axis >= 1, axis >= 2. */
void pgn_aggregate_narrow_avx512(const float *feat, int64_t D, const int64_t *cidx,
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
        for (int64_t d = 0; d < D; ++d) o[d] = acc[d];
        for (int64_t d = 0; d < D; ++d) o[D + d] = acc[32 + d];
        for (int64_t d = 2 * D; d < D2p; ++d) o[d] = 0.0f;
    }
#undef PGN_PE
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

void pgn_std_centre_avx512(const float *feat, int64_t Dp, const int32_t *nr, int64_t K,
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

/* ISO C wants a non-empty translation unit when AVX-512 is off */
typedef int pgn_avx512_unit;
