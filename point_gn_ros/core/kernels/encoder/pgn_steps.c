/* The encoder's steps over a range of a stage's centres: kNN rows, coordinate offsets, the
 * feature-offset std's partials and the aggregation (the ISA kernel chosen by pgn_encode.c).
 * Every centre's result depends on that centre only, so the chunks of a cloud give the
 * same bits on either thread (pgn_helper.c).
 */
#include "pgn_steps.h"

/* The std pass's partials of one centre: the sums of e and e^2 over the offsets e of its
 * K neighbours' feature rows from its own row cf (Dp channels), as floats. s1, s2: Dp
 * floats of scratch (the portable path). Per-channel float partials (4 rows a pass, no
 * horizontal sum per row), reduced once per centre; the caller adds them in double. */
static void std_centre(const float *feat, int64_t Dp, const int32_t *nr, int64_t K,
                       const float *cf, float *s1, float *s2, float *a1, float *a2) {
#if defined(__AVX512F__)
    (void)s1; (void)s2;
    pgn_std_centre_avx512(feat, Dp, nr, K, cf, a1, a2);
#elif defined(PGN_AVX2)
    (void)s1; (void)s2;
    pgn_std_centre_avx2(feat, Dp, nr, K, cf, a1, a2);
#else
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
    float x1 = 0.0f, x2 = 0.0f;
#pragma omp simd reduction(+:x1, x2) aligned(s1, s2 : 64)
    for (int64_t d = 0; d < Dp; ++d) { x1 += s1[d]; x2 += s2[d]; }
    *a1 = x1; *a2 = x2;
#endif
}

/* The kNN rows of centres [c0, c1). A row's search writes 16 int32 of slack past its
 * end, i.e. into the next row: within a chunk that row is searched afterwards, but the
 * next chunk's first row may already be done by the other thread, so a chunk's last row
 * is searched into a private row and copied. */
static void knn_chunk(agg_job *j, int tid, int64_t c0, int64_t c1) {
    const int64_t K = j->K;
    if (c1 - 1 > c0)
        pgn_knn_in(j->px, j->py, j->pz, j->n, j->qx + c0, j->qy + c0, j->qz + c0, c1 - 1 - c0,
                   K, j->nb_out + c0 * K, j->dist[tid], j->keys[tid], j->guess, j->slab);
    pgn_knn_in(j->px, j->py, j->pz, j->n, j->qx + c1 - 1, j->qy + c1 - 1, j->qz + c1 - 1, 1, K,
               j->tail[tid], j->dist[tid], j->keys[tid], j->guess, j->slab);
    memcpy(j->nb_out + (c1 - 1) * K, j->tail[tid], sizeof(int32_t) * (size_t)K);
}

/* Offsets of centres [c0, c1): v = xyz[nb] - centre (K, 3) per centre, and each centre's
 * float sums of v and v^2 into part[2 c], part[2 c + 1] (the caller adds them in double:
 * whichever thread ran a centre, the sums are the same bits). pts (SIMD builds, for
 * lanes_init_t): the neighbours' points go to vx instead. */
static void offsets_centres(const float *xyz, const float *cx, const float *cy,
                            const float *cz, const int32_t *nb, int64_t K, int64_t c0,
                            int64_t c1, float *vx, float *part, int pts) {
    for (int64_t c = c0; c < c1; ++c) {
        const float qx = cx[c], qy = cy[c], qz = cz[c];
        const int32_t *nr = nb + c * K;
        float *v = vx + c * K * 3;
        int64_t t = 0;
#if defined(__AVX512F__) || defined(PGN_AVX2)
        {
            /* 4 floats a neighbour in and out, the 4th (the next point's x; xyz has 4
             * floats of slack) overwritten by the next store and kept out of the sums; the
             * last neighbour by scalars: its 4th float would land in the next centre's
             * row, which the helper thread may have written already */
            const __m128 q4 = _mm_setr_ps(qx, qy, qz, 0.0f);
            const __m128 m3 = _mm_castsi128_ps(_mm_setr_epi32(-1, -1, -1, 0));
            __m128 s1a = _mm_setzero_ps(), s1b = s1a, s2a = s1a, s2b = s1a;
            for (; t + 2 < K; t += 2) {
                const __m128 p4 = _mm_loadu_ps(xyz + (int64_t)nr[t] * 3);
                const __m128 p5 = _mm_loadu_ps(xyz + (int64_t)nr[t + 1] * 3);
                const __m128 d4 = _mm_sub_ps(p4, q4), d5 = _mm_sub_ps(p5, q4);
                _mm_storeu_ps(v + t * 3, pts ? p4 : d4);
                _mm_storeu_ps(v + t * 3 + 3, pts ? p5 : d5);
                const __m128 d = _mm_and_ps(d4, m3), e = _mm_and_ps(d5, m3);
                s1a = _mm_add_ps(s1a, d);
                s1b = _mm_add_ps(s1b, e);
                s2a = _mm_fmadd_ps(d, d, s2a);
                s2b = _mm_fmadd_ps(e, e, s2b);
            }
            for (; t < K; ++t) {
                const float *pj = xyz + (int64_t)nr[t] * 3;
                const __m128 d = _mm_and_ps(
                    _mm_sub_ps(_mm_setr_ps(pj[0], pj[1], pj[2], 0.0f), q4), m3);
                float dv[4];
                _mm_storeu_ps(dv, d);
                for (int a = 0; a < 3; ++a) v[t * 3 + a] = pts ? pj[a] : dv[a];
                s1a = _mm_add_ps(s1a, d);
                s2a = _mm_fmadd_ps(d, d, s2a);
            }
            float a[4], b[4];
            _mm_storeu_ps(a, _mm_add_ps(s1a, s1b));
            _mm_storeu_ps(b, _mm_add_ps(s2a, s2b));
            part[2 * c] = (a[0] + a[1]) + a[2];
            part[2 * c + 1] = (b[0] + b[1]) + b[2];
            continue;
        }
#else
        (void)pts;
#endif
        for (; t < K; ++t) {
            const float *pj = xyz + (int64_t)nr[t] * 3;
            v[t * 3] = pj[0] - qx; v[t * 3 + 1] = pj[1] - qy; v[t * 3 + 2] = pj[2] - qz;
        }
        float a1 = 0.0f, a2 = 0.0f;
#pragma omp simd reduction(+:a1, a2)
        for (int64_t u = 0; u < K * 3; ++u) { a1 += v[u]; a2 += v[u] * v[u]; }
        part[2 * c] = a1;
        part[2 * c + 1] = a2;
    }
}

/* The feature-offset std's partials of centres [c0, c1) into fpart. */
static void std_centres(agg_job *j, int tid, int64_t c0, int64_t c1) {
#ifdef PGN_PROFILE
    const double t0 = pgn_now();
#endif
    for (int64_t c = c0; c < c1; ++c)
        std_centre(j->feat, j->Dp, j->nb + c * j->K, j->K, j->feat + j->cidx[c] * j->Dp,
                   j->mx[tid], j->sm[tid], j->fpart + 2 * c, j->fpart + 2 * c + 1);
#ifdef PGN_PROFILE
    pgn_prof_split(7, t0);
#endif
}

void pgn_phase_chunk(void *job, int tid, int64_t chunk) {
    agg_job *j = job;
    const int64_t c0 = j->S * chunk / j->nchunks, c1 = j->S * (chunk + 1) / j->nchunks;
    if (c1 <= c0) return;
    if (j->knn) {
#ifdef PGN_PROFILE
        const double t0 = pgn_now();
#endif
        knn_chunk(j, tid, c0, c1);
#ifdef PGN_PROFILE
        pgn_prof_split(1, t0);
#endif
        if (!j->offs) return;   /* else these centres' offsets next */
    }
    if (j->offs) {
        offsets_centres(j->xyz, j->qx, j->qy, j->qz, j->nb, j->K, c0, c1, j->vx_out, j->part,
                        j->pts);
        if (j->stdp) std_centres(j, tid, c0, c1);
        return;
    }
    if (j->vx_scale) {   /* these centres' offset rows, by 1 / std, just before their use */
        float *v = j->vx_scale + c0 * j->K * 3;
        const float rx = j->rx;
#pragma omp simd
        for (int64_t u = 0; u < (c1 - c0) * j->K * 3; ++u) v[u] *= rx;
        if (j->scale_only) return;
    }
    j->aggregate(j, tid, c0, c1);
    gelu_rows(j->out + c0 * j->D2p, (c1 - c0) * j->D2p);
}
