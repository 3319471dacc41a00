/* The encoder's steps over a range of a stage's centres (pgn_steps.c): kNN, coordinate
 * offsets, the feature-offset std's partials and the aggregation, as one job type that
 * pgn_encode.c fills and runs whole, or cut into chunks shared with the helper thread
 * (pgn_helper.c).
 */
#ifndef PGN_STEPS_H
#define PGN_STEPS_H

#include "pgn_common.h"
#include "pgn_geom.h"

#ifdef PGN_PROFILE
#include <time.h>
extern double pgn_prof[16];  /* per-phase thread CPU seconds (pgn_encode.c) */
static inline double pgn_now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}
/* The time since t0, spent inside a step (slot 10), counted as a phase of its own: slot. */
static inline void pgn_prof_split(int slot, double t0) {
    const double dt = pgn_now() - t0;
    pgn_prof[slot] += dt;
    pgn_prof[10] -= dt;
}
#endif


struct agg_job;
/* A stage's aggregation over centres [c0, c1) of job j on thread tid (0 caller, 1 helper):
 * rows of pooled values before gelu, zero padded to D2p. */
typedef void (*pgn_aggregate_fn)(const struct agg_job *j, int tid, int64_t c0, int64_t c1);

/* The aggregation variants (kernels/README.md); pgn_dispatch.c maps ISA x variant to its
 * function. */
typedef enum {
    PGN_DIRECT,           /* one exponential per pe channel and neighbour */
    PGN_SEPARABLE,        /* separable Gaussians on the stage's uniform grid (sep_t) */
    PGN_NARROW,           /* 16 < D <= 32: all of a centre's 2 D channels in registers */
    PGN_NARROW_DERIVED,   /* narrow, half the exponentials: the others derived from them */
    PGN_NEIGHBOUR_LANES,  /* 16 < D <= 32: neighbours in the lanes, running products */
    PGN_NVARIANTS
} pgn_variant;

/* A cloud on two threads: the caller and one helper share each stage's
 * aggregation by chunks of centres, claimed from an atomic counter. Every centre's
 * result depends on that centre only, so the split never changes a bit. The caller
 * works through the chunks itself and waits only for chunks the helper has claimed:
 * a helper that is not scheduled in time costs nothing but its wake-up. */
typedef struct agg_job {
    /* kNN job (knn = 1): the stage's points (px, py, pz: n each) and centres (qx, qy, qz),
     * each thread with its own distance / key scratch and a private last row (below);
     * with offs = 1 as well (the encoder's step), each chunk then takes its centres'
     * offsets (below) */
    int knn;
    /* offsets job (offs = 1): the centres' offset rows into vx_out and their per-centre
     * sums of v and v^2 into part (2 S); xyz: the stage's points (AoS). With stdp = 1 also
     * the per-centre partials of the feature-offset std into fpart (2 S): the same
     * centres' rows, so one step instead of two */
    int offs;
    const float *xyz;
    float *vx_out;
    int pts;              /* vx_out gets the neighbours' points (lanes_init_t) */
    int stdp;
    int64_t Dp;
    float *part, *fpart;
    /* aggregation: the centres' offset rows (vx_scale, the same buffer as vx) are scaled
     * by rx = 1 / std first, by the chunk that aggregates them, when set; scale_only: a
     * step that only scales them */
    float *vx_scale;
    float rx;
    int scale_only;
    const float *px, *py, *pz, *qx, *qy, *qz;
    int64_t n;
    float guess;          /* pgn_knn_guess of the points: the same for every chunk */
    const pgn_slab *slab; /* the points in buckets along an axis (pgn_slab.c), or NULL */
    int32_t *nb_out;
    float *dist[2];
    uint64_t *keys[2];
    int32_t *tail[2];
    const float *feat;
    int64_t D, S, K, D2p, PS, nchunks;
    const int64_t *cidx;
    const int32_t *nb;
    const float *vx, *cc;
    const int32_t *ax;
    float r, q;
    float *out;
    sep_t fx[2];          /* per thread: its own A / E scratch */
    float *pe[2], *mx[2], *sm[2];
    const lanes_t *lanes;  /* stage 1 with neighbours in the lanes (SIMD builds), else NULL */
    float *lscr[2];        /* its scratch, per thread */
    const lanes_init_t *ini;  /* stage 1's rows from the points (SIMD builds), or NULL */
    /* the aggregation kernel: pgn_dispatch.c's entry for this build's ISA and the stage's
     * variant (pgn_encode.c chooses it) */
    pgn_aggregate_fn aggregate;
#if defined(__AVX512F__)
    const float *ccs;
    const __mmask16 *m1, *m2;
    float sc;
#elif defined(PGN_AVX2)
    const float *ccs;
    const int32_t *lane_axis;
    float sc;
    const float *cents;   /* this stage's centres of one axis (narrow_derived) */
#endif
} agg_job;

/* Chunk `chunk` (of job->nchunks) of an agg_job on thread tid: centres
 * [S chunk / nchunks, S (chunk + 1) / nchunks). The helper runtime's chunk function. */
void pgn_phase_chunk(void *job, int tid, int64_t chunk);

/* This build's kernel for a variant: its ISA's entry, else the portable one (direct and
 * separable exist for every build); NULL where neither is built. */
pgn_aggregate_fn pgn_kernel_for(pgn_variant v);

#endif
