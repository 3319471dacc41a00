/* The helper thread: a one-cloud batch's steps shared between the caller and one helper
 * thread per process (pgn_encode_with_helper).
 *
 * The helper is started at the first such cloud and kept, so no cloud waits for a thread's
 * creation and first scheduling. Between clouds it sleeps on a
 * condition variable; each cloud first moves it off the caller's CPU (keep_away), and while
 * it serves a cloud it polls for the next step instead of sleeping between steps.
 *
 * One caller at a time has the helper (`busy`); a second caller meanwhile runs its cloud on
 * its own thread. The per-cloud state is therefore one static struct. Nothing here
 * computes; the helper runs each chunk with the caller's SSE control word (rounding,
 * flush-to-zero), so a chunk rounds the same on either thread.
 */
#define _GNU_SOURCE
#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>
#if defined(__SSE__)
#include <xmmintrin.h>  /* _mm_getcsr / _mm_setcsr */
#endif

#include "pgn_helper.h"

/* The helper yields its CPU once it has polled this long without a step: the serial steps
 * between two shared ones (an FPS, the pooling) take tens of us, and a runnable thread of
 * another program on that CPU must not wait for them. */
#define POLL_YIELD_NS 50000

struct pgn_par {
    _Atomic int quit;             /* the cloud is done: the helper leaves it */
    _Atomic int exited;           /* the helper has left the cloud */
    /* The current step (fn, job, nchunks) under a sequence count: 2 gen while step gen is
     * posted, odd while the caller writes the next one. */
    _Atomic uint64_t seq;
    _Atomic(pgn_chunk_fn) fn;
    _Atomic(void *) job;
    _Atomic int64_t nchunks;
    _Atomic uint64_t next;        /* (step generation << 32) | next unclaimed chunk */
    _Atomic int64_t done;         /* chunks of the current step finished */
    uint64_t gen;                 /* the caller's last step generation (caller only) */
    unsigned csr;                 /* the caller's SSE control word */
};

static struct {
    pthread_mutex_t mu;
    pthread_cond_t cv;
    uint64_t posted;              /* clouds posted, under mu */
    int waiting;                  /* a posted cloud not yet taken by the helper, under mu */
    pid_t pid;                    /* the process that started the helper (0: none) */
    pthread_t thread;
#ifdef __linux__
    cpu_set_t allowed;            /* the process's CPUs when the helper started */
#endif
    int away_from;                /* the CPU the helper was last kept off, or -1 */
    struct pgn_par par;           /* the current cloud's state */
} rt;                             /* mu and cv are set up by started() */

static pthread_mutex_t start_mu = PTHREAD_MUTEX_INITIALIZER;
static _Atomic int busy;          /* a caller has the helper */

static inline void cpu_relax(void) {
#if defined(__x86_64__) || defined(__i386__)
    __builtin_ia32_pause();
#elif defined(__aarch64__)
    __asm__ __volatile__("yield");
#endif
}

static int64_t mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* Claim and run chunks of step generation gen until none is left. A claim (the CAS on
 * `next`) succeeds only while step gen has unclaimed chunks, and the caller posts no other
 * step until they are all done: so the step read under an unchanged `seq` is the one
 * claimed from. */
static void work(struct pgn_par *p, uint64_t gen, int tid) {
    const uint64_t s1 = atomic_load(&p->seq);
    if (s1 != 2 * gen) return;    /* another step is posted or being posted */
    pgn_chunk_fn fn = atomic_load(&p->fn);
    void *job = atomic_load(&p->job);
    const int64_t n = atomic_load(&p->nchunks);
    if (atomic_load(&p->seq) != s1) return;
    for (;;) {
        uint64_t v = atomic_load(&p->next);
        if ((v >> 32) != gen || (int64_t)(v & 0xffffffffu) >= n) return;
        if (!atomic_compare_exchange_weak(&p->next, &v, v + 1)) continue;
        fn(job, tid, (int64_t)(v & 0xffffffffu));
        atomic_fetch_add(&p->done, 1);
    }
}

/* The helper's part of one cloud: every step posted until the caller sets quit. */
static void serve(struct pgn_par *p) {
#if defined(__SSE__)
    _mm_setcsr(p->csr);
#endif
    uint64_t seen = 0;
    int64_t idle_since = mono_ns();
    for (int i = 1; !atomic_load(&p->quit); ++i) {
        const uint64_t gen = atomic_load(&p->next) >> 32;
        if (gen != seen) {
            seen = gen;
            work(p, gen, 1);
            idle_since = mono_ns();
            continue;
        }
        cpu_relax();
        if ((i & 255) == 0 && mono_ns() - idle_since > POLL_YIELD_NS) sched_yield();
    }
}

static void *helper_main(void *arg) {
    (void)arg;
    uint64_t seen = 0;
    pthread_mutex_lock(&rt.mu);
    for (;;) {
        while (rt.posted == seen) pthread_cond_wait(&rt.cv, &rt.mu);
        seen = rt.posted;
        const int take = rt.waiting;
        rt.waiting = 0;           /* taken: the caller now waits for `exited` */
        pthread_mutex_unlock(&rt.mu);
        if (take) {
            serve(&rt.par);
            atomic_store(&rt.par.exited, 1);
        }
        pthread_mutex_lock(&rt.mu);
    }
    return NULL;
}

/* Start the helper once per process; 1 if it runs. */
static int started(void) {
    pthread_mutex_lock(&start_mu);
    if (rt.pid != getpid()) {   /* never started, or a forked child (no thread survives) */
        pthread_mutex_init(&rt.mu, NULL);
        pthread_cond_init(&rt.cv, NULL);
        rt.posted = 0;
        rt.waiting = 0;
        rt.away_from = -1;
#ifdef __linux__
        if (sched_getaffinity(0, sizeof(rt.allowed), &rt.allowed) != 0)
            CPU_ZERO(&rt.allowed);          /* keep_away then leaves the helper alone */
#endif
        pthread_attr_t attr;
        pthread_t th;
        if (pthread_attr_init(&attr) == 0) {
            pthread_attr_setdetachstate(&attr, PTHREAD_CREATE_DETACHED);
            if (pthread_create(&th, &attr, helper_main, NULL) == 0) {
                rt.thread = th;
                rt.pid = getpid();
#ifdef __linux__
                pthread_setname_np(th, "pgn_enc_helper");   /* top -H, /proc/PID/task/.../comm */
#endif
            }
            pthread_attr_destroy(&attr);
        }
    }
    const int ok = rt.pid == getpid();
    pthread_mutex_unlock(&start_mu);
    return ok;
}

/* Keep the helper off the caller's CPU (under rt.mu): woken there, the scheduler queued it
 * behind the busy caller for up to a tick while the other CPU idled. */
static void keep_away(void) {
#ifdef __linux__
    const int cpu = sched_getcpu();
    if (cpu < 0 || cpu == rt.away_from || !CPU_ISSET(cpu, &rt.allowed)) return;
    cpu_set_t set = rt.allowed;
    CPU_CLR(cpu, &set);
    if (CPU_COUNT(&set) == 0) return;
    if (pthread_setaffinity_np(rt.thread, sizeof(set), &set) == 0) rt.away_from = cpu;
#endif
}

/* Whether this process may run on one CPU only (read when the helper started). */
static int one_cpu(void) {
#ifdef __linux__
    return CPU_COUNT(&rt.allowed) == 1;
#else
    return 0;
#endif
}

pgn_par *pgn_par_begin(void) {
    if (atomic_exchange(&busy, 1)) return NULL;
    /* On one usable CPU a polling helper would only take turns with its caller. */
    if (!started() || one_cpu()) {
        atomic_store(&busy, 0);
        return NULL;
    }
    struct pgn_par *p = &rt.par;
    atomic_store(&p->quit, 0);
    atomic_store(&p->exited, 0);
    atomic_store(&p->done, 0);
    atomic_store(&p->next, 0);
    atomic_store(&p->seq, 0);
    p->gen = 0;
#if defined(__SSE__)
    p->csr = _mm_getcsr();
#endif
    pthread_mutex_lock(&rt.mu);
    keep_away();
    rt.waiting = 1;
    rt.posted++;
    pthread_cond_signal(&rt.cv);
    pthread_mutex_unlock(&rt.mu);
    return p;
}

void pgn_par_run(pgn_par *p, pgn_chunk_fn fn, void *job, int64_t nchunks) {
    if (!p) {
        for (int64_t i = 0; i < nchunks; ++i) fn(job, 0, i);
        return;
    }
    const uint64_t gen = ++p->gen;
    atomic_store(&p->seq, 2 * gen - 1);
    atomic_store(&p->fn, fn);
    atomic_store(&p->job, job);
    atomic_store(&p->nchunks, nchunks);
    atomic_store(&p->done, 0);
    atomic_store(&p->seq, 2 * gen);
    atomic_store(&p->next, gen << 32);
    work(p, gen, 0);
    for (int spin = 0; atomic_load(&p->done) < nchunks; ++spin)
        if (spin > 64) sched_yield();  /* only chunks the helper is running are left */
}

void pgn_par_end(pgn_par *p) {
    if (!p) return;
    atomic_store(&p->quit, 1);
    pthread_mutex_lock(&rt.mu);
    const int taken = !rt.waiting;
    rt.waiting = 0;                    /* not taken yet: the helper will skip this cloud */
    pthread_mutex_unlock(&rt.mu);
    for (int spin = 0; taken && !atomic_load(&p->exited); ++spin)
        if (spin > 64) sched_yield();  /* the helper must leave before the next cloud */
    atomic_store(&busy, 0);
}
