/* Point-GN stage kernels with AVX2 + FMA intrinsics, for CPUs without AVX-512 (Intel
 * client parts, AMD before Zen 4): the loops of pgn_avx512.c with 8-float lanes. Compiled
 * only where the compiler targets AVX2 and FMA but not AVX-512 (PGN_AVX2, pgn_common.h);
 * elsewhere this file is empty and pgn_encode.c uses the AVX-512 or portable kernels. */
#include "pgn_common.h"

#if defined(PGN_AVX2)
/* Stage aggregation for 16 < D <= 32 (stage 1 of the default encoder, D = 27), as
 * pgn_aggregate_narrow_avx512: lanes [0, 32) are pe channels [0, 32) (offset half), lanes
 * [32, 64) pe channels [D, D + 32) (centre half); Gaussians as 2^-(u s)^2. Sixteen ymm
 * registers do not hold both halves' 16 accumulators and 8 Gaussian vectors, so each half
 * walks the K neighbours on its own (4 vectors, 8 accumulators in registers).
 * ccs: (64,) pe-lane centres times s; lane_axis: (64,) axis of each lane; acc: 64 floats;
 * vx: (S, K, 3) plus one readable float after the last offset. */
void pgn_aggregate_narrow_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, const float *ccs, const int32_t *lane_axis, float s,
                            float *out, float *acc) {
    const int64_t Dp = 32, D2p = padded(2 * D);
    const __m256 vr = _mm256_set1_ps(r);
    const __m128 s4 = _mm_set1_ps(s);
    __m256 cc[8];
    __m256i axi[8];  /* lane -> axis: one permute picks each lane's offset */
    for (int i = 0; i < 8; ++i) {
        axi[i] = _mm256_loadu_si256((const __m256i *)(lane_axis + 8 * i));
        cc[i] = _mm256_loadu_ps(ccs + 8 * i);
    }
    const float invk = 1.0f / (float)K;
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const int32_t *nr = nb + c * K;
        const float *vc = vx + c * K * 3;
        for (int h = 0; h < 2; ++h) {
            __m256 g[4], mx[4], sm[4];
            for (int j = 0; j < 4; ++j) {
                g[j] = _mm256_load_ps(cf + 8 * j);
                mx[j] = _mm256_set1_ps(-INFINITY);
                sm[j] = _mm256_setzero_ps();
            }
            for (int64_t t = 0; t < K; ++t) {
                /* offsets x, y, z (and one float more: vx has slack) times s */
                const __m256 vv = _mm256_castps128_ps256(_mm_mul_ps(_mm_loadu_ps(vc + t * 3), s4));
                const float *row = feat + (int64_t)nr[t] * Dp;
                for (int j = 0; j < 4; ++j) {
                    const int i = 4 * h + j;
                    const __m256 va = _mm256_permutevar8x32_ps(vv, axi[i]);
                    const __m256 u = _mm256_sub_ps(cc[i], va);
                    const __m256 pe = exp2_neg_avx2(_mm256_mul_ps(u, u));
                    /* offset half: (row - cf) r; centre half: cf */
                    const __m256 f = h == 0
                        ? _mm256_mul_ps(_mm256_sub_ps(_mm256_load_ps(row + 8 * j), g[j]), vr)
                        : g[j];
                    const __m256 w = _mm256_mul_ps(_mm256_add_ps(f, pe), pe);
                    mx[j] = _mm256_max_ps(mx[j], w);
                    sm[j] = _mm256_add_ps(sm[j], w);
                }
            }
            const __m256 ik = _mm256_set1_ps(invk);
            for (int j = 0; j < 4; ++j)
                _mm256_storeu_ps(acc + 32 * h + 8 * j, _mm256_fmadd_ps(sm[j], ik, mx[j]));
        }
        float *o = out + c * D2p;
        for (int64_t d = 0; d < D; ++d) o[d] = acc[d];
        for (int64_t d = 0; d < D; ++d) o[D + d] = acc[32 + d];
        for (int64_t d = 2 * D; d < D2p; ++d) o[d] = 0.0f;
    }
}

/* Separable stages with AVX2 (blocks of 8), as pgn_aggregate_separable_avx512's sep_pass: pe is
 * never stored; the pe of a block is A[t, a, m] * (T[m, 0..8) * P[t, a]^(0..8)), the powers
 * by blends of P, P^2, P^4 multiplied in the same order as the AVX-512 masked multiplies.
 * AVX2 has no cheap masked store, so max and sum live in a per-axis padded layout (axis a
 * at a * 8M, lanes past its n centres computed and ignored) and a block never spills into
 * the next axis. G: per lane cf[ch] (ch < D) or cf[ch - D]; RV: r / T where ch < D, else 0;
 * G2: 0 where ch < D, else G / T (T folded out: pgn_aggregate_separable_avx2). */
#ifndef SEP_NT
#define SEP_NT 8  /* neighbours per pass: one max / sum update per block */
#endif
static inline __attribute__((always_inline)) void sep_pass8(
        const float *const *rows, int nt, int64_t t0, int64_t nta, const sep_t *fx,
        const float *G, const float *RV, const float *G2, float *mx, float *sm) {
    const int64_t n = fx->n, M = fx->M;
    const __m256 one = _mm256_set1_ps(1.0f);
    const __m256 b1 = _mm256_castsi256_ps(_mm256_setr_epi32(0, -1, 0, -1, 0, -1, 0, -1));
    const __m256 b2 = _mm256_castsi256_ps(_mm256_setr_epi32(0, 0, -1, -1, 0, 0, -1, -1));
    const __m256 b4 = _mm256_castsi256_ps(_mm256_setr_epi32(0, 0, 0, 0, -1, -1, -1, -1));
    for (int a = 0; a < 3; ++a) {
        __m256 e[SEP_NT];
        for (int i = 0; i < nt; ++i) {
            const int64_t ta = 3 * (t0 + i) + a;
            const __m256 p1 = _mm256_blendv_ps(one, _mm256_set1_ps(fx->E[1 * nta + ta]), b1);
            const __m256 p2 = _mm256_blendv_ps(one, _mm256_set1_ps(fx->E[2 * nta + ta]), b2);
            const __m256 p4 = _mm256_blendv_ps(one, _mm256_set1_ps(fx->E[4 * nta + ta]), b4);
            e[i] = _mm256_mul_ps(_mm256_mul_ps(p1, p2), p4);
        }
        for (int64_t m = 0; m < M; ++m) {
            const int64_t ch = a * n + 8 * m, pa = (a * M + m) * 8;
            const __m256 g = _mm256_load_ps(G + pa);
            const __m256 rv = _mm256_load_ps(RV + pa), g2 = _mm256_load_ps(G2 + pa);
            const int any_off = !_mm256_testz_si256(_mm256_castps_si256(rv),
                                                    _mm256_castps_si256(rv));
            __m256 w[SEP_NT];
            for (int i = 0; i < nt; ++i) {
                /* pe / T: T is folded into RV, G2 and the caller's final scaling */
                const __m256 pe = _mm256_mul_ps(
                    _mm256_set1_ps(fx->A[m * nta + 3 * (t0 + i) + a]), e[i]);
                if (any_off) {
                    /* lanes past D read on into the next row or the table's slack
                     * (pgn_encode.c allocates 16 floats more), finite: times 0 below.
                     * ((row - g) r + pe) pe where ch < D, else (g + pe) pe, as one fma
                     * (axis 0: n <= D channels, all offsets, G2 = 0) */
                    const __m256 row = _mm256_loadu_ps(rows[i] + ch);
                    const __m256 x = _mm256_fmadd_ps(_mm256_sub_ps(row, g), rv,
                                                     a == 0 ? pe : _mm256_add_ps(g2, pe));
                    w[i] = _mm256_mul_ps(x, pe);
                } else {
                    w[i] = _mm256_mul_ps(_mm256_add_ps(g2, pe), pe);
                }
            }
            __m256 wm = w[0], ws = w[0];
            if (nt == SEP_NT) {  /* pairwise trees */
                __m256 tm[SEP_NT], ts[SEP_NT];
                for (int i = 0; i < SEP_NT; ++i) tm[i] = ts[i] = w[i];
                for (int h = SEP_NT / 2; h >= 1; h /= 2)
                    for (int i = 0; i < h; ++i) {
                        tm[i] = _mm256_max_ps(tm[2 * i], tm[2 * i + 1]);
                        ts[i] = _mm256_add_ps(ts[2 * i], ts[2 * i + 1]);
                    }
                wm = tm[0];
                ws = ts[0];
            }
            _mm256_store_ps(mx + pa, _mm256_max_ps(wm, _mm256_load_ps(mx + pa)));
            _mm256_store_ps(sm + pa, _mm256_add_ps(_mm256_load_ps(sm + pa), ws));
        }
    }
}

/* All S centres of a separable stage (fx->B == 8). mx, sm, G, RV, G2, SRC: 3 * 8 * fx->M
 * floats (SRC: int32) each, 32-byte aligned. */
void pgn_aggregate_separable_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, float *out, float *mx, float *sm, float *G, float *RV,
                            float *G2, int32_t *SRC, float *IT, float *T2, sep_t *fx) {
    const int64_t Dp = padded(D), D2 = 2 * D, D2p = padded(D2), nta = 3 * K;
    const int64_t n = fx->n, M = fx->M, np = 3 * 8 * M;
    const float invk = 1.0f / (float)K;
    /* pe = T A e: w = (f + pe) pe = T^2 (f / T + A e) A e (T > 0), so the passes aggregate
     * with RV = r / T, G2 = G / T and the results are scaled by T^2 (encode_one checks the
     * range: tfold_ok) */
    for (int64_t p = 0; p < np; ++p) {
        const int64_t a = p / (8 * M), j = p % (8 * M), ch = a * n + j;
        const float T = fx->T[j];
        IT[p] = 1.0f / T;
        T2[p] = T * T;
        RV[p] = j < n && ch < D ? r / T : 0.0f;
        SRC[p] = j < n ? (int32_t)(ch < D ? ch : ch - D) : -1;  /* G's source channel */
    }
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const int32_t *nr = nb + c * K;
        for (int64_t p = 0; p < np; ++p) {
            G[p] = SRC[p] >= 0 ? cf[SRC[p]] : 0.0f;
            G2[p] = RV[p] != 0.0f ? 0.0f : G[p] * IT[p];
            mx[p] = -INFINITY;
            sm[p] = 0.0f;
        }
        pgn_sep_prepare(fx, vx + c * K * 3, K);
        int64_t t = 0;
        for (; t + SEP_NT <= K; t += SEP_NT) {
            const float *rows[SEP_NT];
            for (int i = 0; i < SEP_NT; ++i) rows[i] = feat + (int64_t)nr[t + i] * Dp;
            sep_pass8(rows, SEP_NT, t, nta, fx, G, RV, G2, mx, sm);
        }
        for (; t < K; ++t) {
            const float *rows[1] = {feat + (int64_t)nr[t] * Dp};
            sep_pass8(rows, 1, t, nta, fx, G, RV, G2, mx, sm);
        }
        float *o = out + c * D2p;
        for (int a = 0; a < 3; ++a)
            for (int64_t j = 0; j < n; ++j) {
                const int64_t p = a * 8 * M + j;
                o[a * n + j] = T2[p] * (mx[p] + sm[p] * invk);
            }
        for (int64_t d = D2; d < D2p; ++d) o[d] = 0.0f;
    }
}

/* Sums of e = row[d] - cf[d] and e^2 over one centre's K neighbour rows, channels
 * [0, Dp), as pgn_std_centre_avx512: chunks of up to 4 vectors whose 8 partial sums stay
 * in registers over all K rows (8 independent add chains hide the add latency). */
#define PGN_STDCHUNK(NV)                                                                 \
    static inline void stdchunk##NV(const float *feat, int64_t Dp, const int32_t *nr,    \
                                    int64_t K, const float *cf, __m256 *t1, __m256 *t2) { \
        __m256 a1[NV], a2[NV], g[NV];                                                    \
        for (int v = 0; v < NV; ++v) {                                                   \
            g[v] = _mm256_load_ps(cf + 8 * v);                                           \
            a1[v] = a2[v] = _mm256_setzero_ps();                                         \
        }                                                                                \
        for (int64_t t = 0; t < K; ++t) {                                                \
            const float *r0 = feat + (int64_t)nr[t] * Dp;                                \
            for (int v = 0; v < NV; ++v) {                                               \
                const __m256 e0 = _mm256_sub_ps(_mm256_load_ps(r0 + 8 * v), g[v]);       \
                a1[v] = _mm256_add_ps(a1[v], e0);                                        \
                a2[v] = _mm256_fmadd_ps(e0, e0, a2[v]);                                  \
            }                                                                            \
        }                                                                                \
        for (int v = 0; v < NV; ++v) {                                                   \
            *t1 = _mm256_add_ps(*t1, a1[v]);                                             \
            *t2 = _mm256_add_ps(*t2, a2[v]);                                             \
        }                                                                                \
    }
PGN_STDCHUNK(1)
PGN_STDCHUNK(2)
PGN_STDCHUNK(3)
PGN_STDCHUNK(4)
#undef PGN_STDCHUNK

static inline float hsum8(__m256 v) {
    __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    s = _mm_add_ss(s, _mm_movehdup_ps(s));
    return _mm_cvtss_f32(s);
}

void pgn_std_centre_avx2(const float *feat, int64_t Dp, const int32_t *nr, int64_t K,
                         const float *cf, float *a1, float *a2) {
    __m256 t1 = _mm256_setzero_ps(), t2 = t1;
    int64_t v = 0;
    const int64_t nv = Dp / 8;
    for (; v + 4 <= nv; v += 4) stdchunk4(feat + 8 * v, Dp, nr, K, cf + 8 * v, &t1, &t2);
    switch (nv - v) {
        case 3: stdchunk3(feat + 8 * v, Dp, nr, K, cf + 8 * v, &t1, &t2); break;
        case 2: stdchunk2(feat + 8 * v, Dp, nr, K, cf + 8 * v, &t1, &t2); break;
        case 1: stdchunk1(feat + 8 * v, Dp, nr, K, cf + 8 * v, &t1, &t2); break;
        default: break;
    }
    *a1 = hsum8(t1);
    *a2 = hsum8(t2);
}
#endif

/* ISO C wants a non-empty translation unit when AVX2 is off */
typedef int pgn_avx2_unit;
