/* Point-GN encoder, one cloud at a time, fused: no (S, k, D) tensor is ever built. This file
 * holds the stage loop (work space, FPS, the steps' set-up and kernel choice, pooling) and
 * the entry points; the steps over a range of centres are in pgn_steps.c.
 *
 * Results are a pure function of one cloud, whatever the batch or thread, so batches are
 * invariant; a one-cloud batch may share its stages with the helper thread
 * (pgn_encode_with_helper, pgn_helper.c), bit-identically.
 */
#include "pgn_helper.h"
#include "pgn_steps.h"

int pgn_abi_version(void) { return 3; }

/* Lanes of the stage kernels this build runs: 16 (AVX-512), 8 (AVX2 + FMA), 0 (portable C). */
int pgn_simd_width(void) {
#if defined(__AVX512F__)
    return 16;
#elif defined(PGN_AVX2)
    return 8;
#else
    return 0;
#endif
}

#ifdef PGN_PROFILE
double pgn_prof[16];  /* per-phase thread CPU seconds; slots: bench_cmd.PROFILE_SLOTS */
#define TIC(i) double _t##i = pgn_now()
#define TOC(i, slot) pgn_prof[slot] += pgn_now() - _t##i
#else
#define TIC(i)
#define TOC(i, slot)
#endif

typedef struct {
    int64_t num_points, init_dim, stages, k;
    float sigma;
} pgn_cfg;

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

/* 1 / (std + 1e-5) of count values from per-centre float partials part[2 c], part[2 c + 1]
 * (their sum and sum of squares), added in double in centre order: the same bits whichever
 * thread made which partials. */
static float inv_std(const float *part, int64_t S, double count) {
    double s1 = 0.0, s2 = 0.0;
    for (int64_t c = 0; c < S; ++c) { s1 += part[2 * c]; s2 += part[2 * c + 1]; }
    double var = (s2 - s1 * s1 / count) / (count - 1.0);
    if (var < 0.0) var = 0.0;
    return (float)(1.0 / (sqrt(var) + 1e-5));
}

#if defined(PGN_NO_INI)
#define PGN_INI_ROWS 0  /* for A/B timing: stage 1 reads and transposes its rows */
#else
#define PGN_INI_ROWS 1
#endif

/* 64-byte aligned, not zeroed: for the buffers every row of which is written before it is
 * read (the offsets, the kNN rows) */
static void *xalloc_raw(size_t bytes) {
    const size_t sz = (bytes + 63) / 64 * 64;
    return aligned_alloc(64, sz ? sz : 64);
}

static void *xalloc(size_t bytes) {
    /* 64-byte aligned, zeroed: padding lanes stay 0 (they enter sums as 0 - 0) */
    void *p = xalloc_raw(bytes);
    if (p) memset(p, 0, (bytes + 63) / 64 * 64);
    return p;
}



/* Whether a stage of input width D runs with neighbours in the lanes: only 16 < D <= 32,
 * where no separable plan applies (B = 0) and a block plan is safe; lanes, b, T filled. */
static int lanes_plan(int64_t D, int64_t nc, float q, int B, lanes_t *lanes, float *b, float *T) {
#if (defined(__AVX512F__) || defined(PGN_AVX2)) && !defined(PGN_NO_NEIGHBOUR_LANES)
    return !B && D > 16 && D <= 32 && pgn_lanes_plan(nc, q, lanes, b, T);
#else
    (void)D; (void)nc; (void)q; (void)B; (void)lanes; (void)b; (void)T;
    return 0;
#endif
}

/* The aggregation variant of a stage of input width D (pgn_dispatch.c's table): B, the
 * separable plan's block (0: none), use_lanes from lanes_plan. */
static pgn_variant stage_variant(int64_t D, float q, int B, int use_lanes) {
    (void)q;
    if (use_lanes) return PGN_NEIGHBOUR_LANES;
    if (B) return PGN_SEPARABLE;
    if (D > 16 && D <= 32) {
#if defined(PGN_AVX2) && !defined(PGN_NO_NARROW) && !defined(PGN_NO_NARROW_DERIVED)
        if (pgn_narrow_derived_ok(D, q)) return PGN_NARROW_DERIVED;
#endif
#if (defined(__AVX512F__) || defined(PGN_AVX2)) && !defined(PGN_NO_NARROW)
        return PGN_NARROW;
#endif
    }
    return PGN_DIRECT;
}

/* The aggregation variant each stage of an encoder (init_dim, stages, sigma) runs in this
 * build: out (stages) pgn_variant codes (pgn_variant_name). The choice depends on the
 * stage's width and sigma only, never on the cloud. Returns 0, or -1 when out of memory. */
int pgn_stage_variants(int64_t init_dim, int64_t stages, float sigma, int32_t *out) {
    const float q = -0.5f / (sigma * sigma);
    const int64_t Mmax = ((init_dim << stages) / 3 + 7) / 8;
    float *b = xalloc(sizeof(float) * (size_t)Mmax), *C = xalloc(sizeof(float) * (size_t)Mmax);
    float *T = xalloc(sizeof(float) * (size_t)(Mmax + 1) * 16);
    int rc = b && C && T ? 0 : -1;
    for (int64_t st = 0, D = init_dim; !rc && st < stages; ++st, D *= 2) {
        const int64_t nc = 2 * D / 3;
        sep_t fx;
        lanes_t lanes;
        float lanes_b[PGN_LANES_MAXC], lanes_T[PGN_LANES_MAXC];
        const int B = pgn_sep_plan(nc, q, &fx, b, C, T);
        out[st] = (int32_t)stage_variant(D, q, B, lanes_plan(D, nc, q, B, &lanes, lanes_b,
                                                             lanes_T));
    }
    free(b); free(C); free(T);
    return rc;
}

/* Encode one cloud. xyz: (num_points, 3); cents: concatenated Gaussian centre
 * tables (init block of init_dim/3, then 2*D_i/3 per stage); out: (feature_dim,).
 * par: the helper thread's runtime (pgn_helper.c), or NULL.
 * Returns 0, or -1 when out of memory. */
static int encode_one(const float *xyz_in, const pgn_cfg *cfg, const float *cents, float *out,
                      pgn_par *par) {
    TIC(11);
    const int64_t N = cfg->num_points, D0 = cfg->init_dim;
    const float q = -0.5f / (cfg->sigma * cfg->sigma);
    const int64_t S1 = N / 2;
    const int64_t K1 = cfg->k < N ? cfg->k : N;
    const int64_t Dmax = D0 << cfg->stages;  /* widest 2D */
    /* Every stage holds S_i rows of padded(2 D_i) <= N * D0 + S_i * PAD features. */
    const int64_t fsz = N * (D0 + PAD);
    /* + 16: kernels that read a row's last vector whole (pgn_avx512_separable.c) stay inside;
     * not zeroed: every row a stage reads is written first, padding lanes as 0 */
    float *featA = xalloc_raw(sizeof(float) * (size_t)(fsz + 16));
    float *featB = xalloc_raw(sizeof(float) * (size_t)(fsz + 16));
    float *xyz = xalloc(sizeof(float) * ((size_t)N * 3 + 4));  /* + 4: offsets' 4-float loads */
    float *cxyz = xalloc(sizeof(float) * (size_t)N * 3);
    float *soa = xalloc(sizeof(float) * (size_t)N * 6);
    float *scratch = xalloc(sizeof(float) * (size_t)N);
    /* + 8: the AVX2 stage 1 loads each neighbour's 3 offsets as 4 floats */
    float *vx = xalloc_raw(sizeof(float) * ((size_t)S1 * K1 * 3 + 8));
    /* one scratch vector / pe buffer: a multiple of 64 bytes, since the vector loops
     * declare their pointers 64-byte aligned */
    const int64_t VS = padded(Dmax + 4 * PAD), PS = VS;
    float *vec = xalloc(sizeof(float) * (size_t)VS * 3);
    float *pe = xalloc(sizeof(float) * (size_t)PS * 6);
    int32_t *ax = xalloc(sizeof(int32_t) * (size_t)VS);
    int64_t *cidx = xalloc(sizeof(int64_t) * (size_t)S1);
    const int64_t Mmax = (Dmax / 3 + 7) / 8;
    float *sepb = xalloc(sizeof(float) * (size_t)Mmax);
    float *sepC = xalloc(sizeof(float) * (size_t)Mmax);
    float *sepT = xalloc(sizeof(float) * (size_t)(Mmax + 1) * 16);
    float *sepA = xalloc(sizeof(float) * (size_t)K1 * 3 * Mmax);
    /* rows 0..8 of E, then AVX-512's E16 (K1, 16) 64-byte aligned (pgn_avx512_separable.c) */
    const size_t sepEn = (size_t)K1 * 3 * (9 + 16) + 16;
    float *sepE = xalloc(sizeof(float) * sepEn);
    /* the helper's own scratch (pe buffers, mx / sm, separable A / E) */
    const int npar = par ? 2 : 1;
    float *pe2 = par ? xalloc(sizeof(float) * (size_t)PS * 6) : NULL;
    float *vec2 = par ? xalloc(sizeof(float) * (size_t)VS * 2) : NULL;
    float *sepA2 = par ? xalloc(sizeof(float) * (size_t)K1 * 3 * Mmax) : NULL;
    float *sepE2 = par ? xalloc(sizeof(float) * sepEn) : NULL;
    /* the helper's kNN scratch, and a private last row per thread (knn_chunk) */
    float *scratch2 = par ? xalloc(sizeof(float) * (size_t)N) : NULL;
    uint64_t *keys2 = par ? xalloc(sizeof(uint64_t) * (size_t)(2 * N + 32)) : NULL;
    int32_t *tails = xalloc(sizeof(int32_t) * (size_t)(npar * (K1 + 16)));
    /* per-centre partial sums: feature offsets (parts), coordinate offsets (oparts) */
    float *parts = xalloc(sizeof(float) * (size_t)(2 * S1));
    float *oparts = xalloc(sizeof(float) * (size_t)(2 * S1));
#if defined(__AVX512F__) || defined(PGN_AVX2)
    /* stage 1 with neighbours in the lanes: its scratch per thread */
    const int64_t LS = pgn_lanes_scratch(K1);
    float *lscr = xalloc(sizeof(float) * (size_t)LS * (size_t)npar);
#else
    float *lscr = NULL;
#endif
    int32_t *nb = xalloc_raw(sizeof(int32_t) * (size_t)(S1 * K1 + 16));
    uint64_t *keys = xalloc(sizeof(uint64_t) * (size_t)(2 * N + 32));
    float *slabbuf = xalloc(sizeof(float) * (size_t)pgn_slab_floats(N));
    int rc = 0;
    TOC(11, 11);
#if defined(__AVX512F__) || defined(PGN_AVX2)
    if (!lscr) {
        rc = -1;
        goto done;
    }
#endif
    if (!featA || !featB || !xyz || !cxyz || !soa || !scratch || !vx || !vec || !ax || !cidx
        || !nb || !keys || !slabbuf || !pe || !sepb || !sepC || !sepT || !sepA || !sepE
        || !parts || !oparts || !tails
        || (npar == 2 && (!pe2 || !vec2 || !sepA2 || !sepE2 || !scratch2 || !keys2))) {
        rc = -1;
        goto done;
    }
    memset(vx + (size_t)S1 * K1 * 3, 0, sizeof(float) * 8);  /* the slack read as a 4th float */
    /* the feature tables' slack past any stage's last row, which whole-row loads reach */
    memset(featA + fsz, 0, sizeof(float) * 16);
    memset(featB + fsz, 0, sizeof(float) * 16);
    float *cc = vec, *mx = vec + VS, *sm = vec + 2 * VS;
    memcpy(xyz, xyz_in, sizeof(float) * (size_t)N * 3);
    /* initial embedding: (N, padded(D0)) */
    TIC(8);
    {
        const int64_t n0 = D0 / 3, D0p = padded(D0);
        for (int64_t i = 0; i < N; ++i) {
            gpe3(xyz + i * 3, cents, n0, q, featA + i * D0p);
            for (int64_t d = 3 * n0; d < D0p; ++d) featA[i * D0p + d] = 0.0f;
        }
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
        /* the points in buckets along their widest axis, where that pays (pgn_slab.c):
         * FPS updates, and kNN searches, only the buckets near a point */
        pgn_slab slab;
        const pgn_slab *sl = NULL;
#if !defined(PGN_NO_SLAB)
        TIC(12);
        sl = pgn_slab_build(x, y, z, n, K, slabbuf, &slab) ? &slab : NULL;
        TOC(12, 10);
#endif
        TIC(1);
#if defined(PGN_NO_FPS_SLAB)
        pgn_fps_in(xyz, x, y, z, n, S, cidx, scratch, NULL);
#else
        pgn_fps_in(xyz, x, y, z, n, S, cidx, scratch, sl);
#endif
        TOC(1, 0);
        float *cx = soa + 3 * n, *cy = cx + S, *cz = cy + S;
        for (int64_t c = 0; c < S; ++c) {
            cx[c] = x[cidx[c]]; cy[c] = y[cidx[c]]; cz[c] = z[cidx[c]];
            cxyz[c * 3] = cx[c]; cxyz[c * 3 + 1] = cy[c]; cxyz[c * 3 + 2] = cz[c];
        }
        /* the separable form's blocks (pgn_stage_plan.c), 0 where it is not used */
        sep_t fxs;
        const int B = pgn_sep_plan(nc, q, &fxs, sepb, sepC, sepT);
#if (defined(__AVX512F__) || defined(PGN_AVX2)) && !defined(PGN_NO_NEIGHBOUR_LANES)
        /* stage 1 (16 < D <= 32) with neighbours in the lanes where a block plan is safe */
        lanes_t lanes;
        float lanes_b[PGN_LANES_MAXC], lanes_T[PGN_LANES_MAXC];
        const int use_lanes = lanes_plan(D, nc, q, B, &lanes, lanes_b, lanes_T);
        /* on the initial embedding, its rows from the points (lanes_init_t) */
        lanes_t ilanes;
        float ilanes_b[PGN_LANES_MAXC], ilanes_T[PGN_LANES_MAXC];
        lanes_init_t ini = {&ilanes, xyz, 1.0f};
        const int use_ini = use_lanes && st == 0 && PGN_INI_ROWS
                            && pgn_lanes_plan(D / 3, q, &ilanes, ilanes_b, ilanes_T);
#else
        const int use_lanes = 0;
#endif
        /* each chunk of centres: their kNN rows, then their offset rows and float sums of
         * v and v^2 and of the feature offsets e and e^2 (added below in double in centre
         * order), in one step that the helper may share; the aggregation's
         * chunks scale their own offset rows by 1 / std */
        TIC(3);
        /* 16 chunks on two threads: a claimed chunk is short, so the caller never waits
         * long for a helper that was descheduled mid-chunk */
        const int64_t nch = par ? (S < 16 ? S : 16) : 1;
        agg_job oj;
        memset(&oj, 0, sizeof(oj));
        oj.knn = 1;
        oj.px = x; oj.py = y; oj.pz = z; oj.n = n;
        oj.guess = pgn_knn_guess(x, y, z, n, K);
        oj.slab = sl;
        oj.nb_out = nb;
        oj.dist[0] = scratch; oj.dist[1] = scratch2;
        oj.keys[0] = keys; oj.keys[1] = keys2;
        oj.tail[0] = tails; oj.tail[1] = par ? tails + K1 + 16 : NULL;
        oj.offs = 1;
#if (defined(__AVX512F__) || defined(PGN_AVX2)) && !defined(PGN_NO_NEIGHBOUR_LANES)
        oj.pts = use_ini;
#endif
        oj.xyz = xyz; oj.qx = cx; oj.qy = cy; oj.qz = cz; oj.nb = nb; oj.S = S; oj.K = K;
        oj.vx_out = vx; oj.part = oparts; oj.nchunks = nch;
        oj.stdp = 1;
        oj.feat = feat; oj.Dp = Dp; oj.cidx = cidx; oj.fpart = parts;
        oj.mx[0] = mx; oj.sm[0] = sm; oj.mx[1] = vec2; oj.sm[1] = vec2 ? vec2 + VS : NULL;
        pgn_par_run(par, pgn_phase_chunk, &oj, nch);
        const float rx = inv_std(oparts, S, (double)(S * K * 3));
        const float rf = inv_std(parts, S, (double)(S * K * D));
        TOC(3, 10);
        TIC(4);
        sep_t *fx = NULL;
        if (B) {
            fxs.A = sepA;
            fxs.E = sepE;
            fx = &fxs;
        }
        agg_job job;
        memset(&job, 0, sizeof(job));
        job.feat = feat; job.D = D; job.S = S; job.K = K; job.D2p = D2p; job.PS = PS;
        job.cidx = cidx; job.nb = nb; job.vx = vx; job.cc = cc; job.ax = ax; job.r = rf;
        job.vx_scale = vx; job.rx = rx;
        job.q = q; job.out = nfeat;
        job.nchunks = nch;
        job.pe[0] = pe; job.mx[0] = mx; job.sm[0] = sm;
        job.pe[1] = pe2; job.mx[1] = vec2; job.sm[1] = vec2 ? vec2 + VS : NULL;
        if (fx) {
            job.fx[0] = *fx;
            job.fx[1] = *fx;
            job.fx[1].A = sepA2;
            job.fx[1].E = sepE2;
        }
        const pgn_variant v = stage_variant(D, q, B, use_lanes);
        const int narrow = v == PGN_NARROW || v == PGN_NARROW_DERIVED;
        (void)narrow;
#if defined(__AVX512F__)
        const float sc = sqrtf(-q * 1.44269504088896341f);
        float ccs[64];
        __mmask16 m1[4] = {0}, m2[4] = {0};
        if (narrow) {
            /* register-resident path; pe lanes: channels [0, 32) and [D, D + 32) */
            for (int i = 0; i < 64; ++i) {
                const int64_t ch = i < 32 ? i : D + (i - 32);
                const int axis = ch < D2 ? (int)(ch / nc) : 0;
                ccs[i] = ch < D2 ? cents[ch % nc] * sc : 0.0f;
                if (axis >= 1) m1[i / 16] |= (__mmask16)(1u << (i % 16));
                if (axis >= 2) m2[i / 16] |= (__mmask16)(1u << (i % 16));
            }
            job.ccs = ccs; job.m1 = m1; job.m2 = m2; job.sc = sc;
        }
#elif defined(PGN_AVX2)
        const float sc = sqrtf(-q * 1.44269504088896341f);
        float ccs[64];
        int32_t lane_axis[64];
        if (narrow) {
            /* the same lanes as the AVX-512 path, axis per lane instead of masks */
            for (int i = 0; i < 64; ++i) {
                const int64_t ch = i < 32 ? i : D + (i - 32);
                lane_axis[i] = ch < D2 ? (int32_t)(ch / nc) : 0;
                ccs[i] = ch < D2 ? cents[ch % nc] * sc : 0.0f;
            }
            job.ccs = ccs; job.lane_axis = lane_axis; job.sc = sc;
            job.cents = cents;
        }
#endif
#if (defined(__AVX512F__) || defined(PGN_AVX2)) && !defined(PGN_NO_NEIGHBOUR_LANES)
        if (use_lanes) {
            job.lanes = &lanes;
            job.lscr[0] = lscr;
            job.lscr[1] = par ? lscr + LS : NULL;
        }
        if (use_ini) {  /* vx holds the points: not scaled */
            ini.rx = rx;
            job.ini = &ini;
            job.vx_scale = NULL;
        }
#endif
#if defined(PGN_AVX2)
        if (narrow) {
            /* these kernels read a float or more past a centre's offset rows, into rows the
             * other thread may be scaling: scaled in a step of their own first */
            agg_job xj;
            memset(&xj, 0, sizeof(xj));
            xj.S = S; xj.K = K; xj.nchunks = job.nchunks;
            xj.vx_scale = vx; xj.rx = rx; xj.scale_only = 1;
            pgn_par_run(par, pgn_phase_chunk, &xj, xj.nchunks);
            job.vx_scale = NULL;
        }
#endif
        if (v == PGN_DIRECT) {
            /* the direct kernel's per-channel centre and axis (padding lanes: ignored) */
            for (int64_t d = 0; d < VS; ++d) { cc[d] = 0.0f; ax[d] = 0; }
            for (int64_t a = 0, d = 0; a < 3; ++a)
                for (int64_t j = 0; j < nc; ++j, ++d) { cc[d] = cents[j]; ax[d] = (int32_t)a; }
        }
        job.aggregate = pgn_kernel_for(v);
        pgn_par_run(par, pgn_phase_chunk, &job, job.nchunks);
        TOC(4, 3 + st);
        TIC(9);
        cents += nc;
        /* global max and mean over centres, 64 channels at a time in registers (each
         * channel's sum still in centre order) */
        for (int64_t d0 = 0; d0 < D2; d0 += 64) {
            float mxb[64], smb[64];
            const int64_t nd = D2 - d0 < 64 ? D2 - d0 : 64;
            for (int64_t d = 0; d < 64; ++d) { mxb[d] = -INFINITY; smb[d] = 0.0f; }
            for (int64_t c = 0; c < S; ++c) {
                const float *restrict rr = nfeat + c * D2p + d0;
#pragma omp simd
                for (int64_t d = 0; d < nd; ++d) {
                    mxb[d] = rr[d] > mxb[d] ? rr[d] : mxb[d];
                    smb[d] += rr[d];
                }
            }
            for (int64_t d = 0; d < nd; ++d) { o[d0 + d] = mxb[d]; o[D2 + d0 + d] = smb[d] / (float)S; }
        }
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
    free(sepb); free(sepC); free(sepT); free(sepA); free(sepE);
    free(pe2); free(vec2); free(sepA2); free(sepE2); free(scratch2); free(keys2); free(tails);
    free(parts); free(oparts); free(lscr); free(slabbuf);
    return rc;
}

/* gelu of x (n) in place by the encoder's own code (gelu_rows), 16 at a time through an
 * aligned buffer: for the tests. */
void pgn_gelu(float *x, int64_t n) {
    float buf[16] __attribute__((aligned(64)));
    for (int64_t i = 0; i < n; i += 16) {
        const int64_t m = n - i < 16 ? n - i : 16;
        memset(buf, 0, sizeof(buf));
        memcpy(buf, x + i, sizeof(float) * (size_t)m);
        gelu_rows(buf, 16);
        memcpy(x + i, buf, sizeof(float) * (size_t)m);
    }
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

/* One cloud on the calling thread plus the process's helper thread (pgn_helper.c), which
 * shares the kNN, std and aggregation steps; bit-identical to pgn_encode. Runs on one
 * thread when another caller has the helper or no helper can start. Returns 0, or -1 when
 * out of memory. */
int pgn_encode_with_helper(const float *xyz, int64_t num_points, int64_t init_dim,
                           int64_t stages, int64_t k, float sigma, const float *cents,
                           int64_t feature_dim, float *out) {
    (void)feature_dim;
    pgn_cfg cfg = {num_points, init_dim, stages, k, sigma};
    pgn_par *par = pgn_par_begin();
    const int rc = encode_one(xyz, &cfg, cents, out, par);
    pgn_par_end(par);
    return rc;
}
