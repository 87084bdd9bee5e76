/* Hand-written C yardsticks for the top's dopri5 against its rk4: how many times rk4's cost an adaptive
 * Dormand-Prince step costs when written the way ../shared/limit/ens.c writes rk4 (members in blocks, a block's
 * state in L1, the member loop vectorized with `omp simd`, OpenMP over blocks). analysis/bench_dopri5.py
 * compiles this with gcc -O3 -march=native -ffast-math -fopenmp (see C_FLAGS there) and times both beside
 * ensemble's kernels. A member's stages stay in registers: one pass per trial step, as ens.c's rk4 (a form with
 * ensemble's layout, stages outside and members inside, took 11x its rk4 when tried, against this one's 9x to
 * 10x). The controller's powers are one exp and one log, glibc's vector versions (libmvec).
 *
 * Right-hand side (ensemble.scenes.top): w1' = -p w3 w2 - r1 w1, w2' = p w3 w1 - r1 w2, w3' = -r3 w3.
 * Step control as ensemble's (ensemble.engine.blocks.control_step): RMS error norm over atol + rtol
 * max(|y|, |y_new|); PI controller h clip(safety err^-alpha err_previous^beta, min_factor, max_factor), at most
 * 1 after a rejection, max(min_factor, safety err^-alpha) on a rejection; each member's steps clipped to land on
 * every saved time, and members there wait for the rest of their block. Every member runs alone: no
 * instruction mixes members.
 */
#include <math.h>
#include <omp.h>

#define BS 128 /* members per block */

static inline void rhs(double p, double r1, double r3, double y1, double y2, double y3,
                       double *d1, double *d2, double *d3)
{
    double pw = p * y3;
    *d1 = -pw * y2 - r1 * y1;
    *d2 = pw * y1 - r1 * y2;
    *d3 = -r3 * y3;
}

/* Fixed steps h, n_save - 1 intervals of steps_per_save steps; w (3, M) in and out. */
void top_rk4(long M, long n_save, long steps_per_save, double h, double *restrict w, const double *restrict rate)
{
    long blocks = M / BS; /* caller pads M to a multiple of BS */
    #pragma omp parallel for schedule(static)
    for (long b = 0; b < blocks; b++) {
        double y1[BS], y2[BS], y3[BS], p[BS], r1[BS], r3[BS];
        for (int l = 0; l < BS; l++) {
            long j = b * BS + l;
            y1[l] = w[j]; y2[l] = w[M + j]; y3[l] = w[2 * M + j];
            p[l] = rate[j]; r1[l] = rate[M + j]; r3[l] = rate[2 * M + j];
        }
        for (long step = 0; step < (n_save - 1) * steps_per_save; step++) {
            #pragma omp simd
            for (int l = 0; l < BS; l++) {
                double a1, a2, a3, b1, b2, b3, c1, c2, c3, e1, e2, e3;
                double Y1 = y1[l], Y2 = y2[l], Y3 = y3[l];
                rhs(p[l], r1[l], r3[l], Y1, Y2, Y3, &a1, &a2, &a3);
                rhs(p[l], r1[l], r3[l], Y1 + 0.5 * h * a1, Y2 + 0.5 * h * a2, Y3 + 0.5 * h * a3, &b1, &b2, &b3);
                rhs(p[l], r1[l], r3[l], Y1 + 0.5 * h * b1, Y2 + 0.5 * h * b2, Y3 + 0.5 * h * b3, &c1, &c2, &c3);
                rhs(p[l], r1[l], r3[l], Y1 + h * c1, Y2 + h * c2, Y3 + h * c3, &e1, &e2, &e3);
                y1[l] = Y1 + h / 6.0 * (a1 + 2.0 * (b1 + c1) + e1);
                y2[l] = Y2 + h / 6.0 * (a2 + 2.0 * (b2 + c2) + e2);
                y3[l] = Y3 + h / 6.0 * (a3 + 2.0 * (b3 + c3) + e3);
            }
        }
        for (int l = 0; l < BS; l++) {
            long j = b * BS + l;
            w[j] = y1[l]; w[M + j] = y2[l]; w[2 * M + j] = y3[l];
        }
    }
}

/* Dormand-Prince 5(4) with FSAL, every member its own step; w (3, M) in and out; counts (3, M) out: accepted
 * and rejected steps, and the trial steps the member's block ran (its own, and those it waited through while
 * others reached a saved time); h0: first trial step (s). */
void top_dopri5(long M, long n_save, double save_dt, double rtol, double atol, double h0,
                double alpha, double beta, double safety, double min_factor, double max_factor,
                double *restrict w, const double *restrict rate, double *restrict counts)
{
    const double a21 = 1.0 / 5,
        a31 = 3.0 / 40, a32 = 9.0 / 40,
        a41 = 44.0 / 45, a42 = -56.0 / 15, a43 = 32.0 / 9,
        a51 = 19372.0 / 6561, a52 = -25360.0 / 2187, a53 = 64448.0 / 6561, a54 = -212.0 / 729,
        a61 = 9017.0 / 3168, a62 = -355.0 / 33, a63 = 46732.0 / 5247, a64 = 49.0 / 176, a65 = -5103.0 / 18656,
        a71 = 35.0 / 384, a73 = 500.0 / 1113, a74 = 125.0 / 192, a75 = -2187.0 / 6784, a76 = 11.0 / 84,
        e1 = 71.0 / 57600, e3 = -71.0 / 16695, e4 = 71.0 / 1920, e5 = -17253.0 / 339200, e6 = 22.0 / 525,
        e7 = -1.0 / 40;
    const double log_first = log(1e-4); /* the error remembered before a member's first accepted step */
    #pragma omp parallel for schedule(static)
    for (long b = 0; b < M / BS; b++) {
        double y1[BS], y2[BS], y3[BS], k1[BS], k2[BS], k3[BS], p[BS], r1[BS], r3[BS];
        double time[BS], h[BS], previous[BS], rejected_last[BS], accepted[BS], rejected[BS];
        long block_steps = 0;
        for (int l = 0; l < BS; l++) {
            long j = b * BS + l;
            y1[l] = w[j]; y2[l] = w[M + j]; y3[l] = w[2 * M + j];
            p[l] = rate[j]; r1[l] = rate[M + j]; r3[l] = rate[2 * M + j];
            rhs(p[l], r1[l], r3[l], y1[l], y2[l], y3[l], &k1[l], &k2[l], &k3[l]);
            time[l] = 0.0; h[l] = h0; previous[l] = log_first; rejected_last[l] = 0.0;
            accepted[l] = 0.0; rejected[l] = 0.0;
        }
        for (long i = 1; i < n_save; i++) {
            const double target = i * save_dt;
            for (int left = BS; left > 0; block_steps++) {
                left = 0;
                #pragma omp simd reduction(+:left)
                for (int l = 0; l < BS; l++) {
                    /* every value loaded up front and every row stored: a "new or old" store is then a blend */
                    const double P = p[l], R1 = r1[l], R3 = r3[l], Y1 = y1[l], Y2 = y2[l], Y3 = y3[l];
                    const double T = time[l], H = h[l], log_previous = previous[l], rejected_before = rejected_last[l];
                    const double q11 = k1[l], q12 = k2[l], q13 = k3[l];
                    const double remaining = target - T;
                    const int moving = remaining > 0.0;
                    const double s = moving ? fmin(H, remaining) : 0.0;
                    double q21, q22, q23, q31, q32, q33, q41, q42, q43, q51, q52, q53, q61, q62, q63, q71, q72, q73;
                    rhs(P, R1, R3, Y1 + s * a21 * q11, Y2 + s * a21 * q12, Y3 + s * a21 * q13, &q21, &q22, &q23);
                    rhs(P, R1, R3, Y1 + s * (a31 * q11 + a32 * q21), Y2 + s * (a31 * q12 + a32 * q22),
                        Y3 + s * (a31 * q13 + a32 * q23), &q31, &q32, &q33);
                    rhs(P, R1, R3, Y1 + s * (a41 * q11 + a42 * q21 + a43 * q31),
                        Y2 + s * (a41 * q12 + a42 * q22 + a43 * q32),
                        Y3 + s * (a41 * q13 + a42 * q23 + a43 * q33), &q41, &q42, &q43);
                    rhs(P, R1, R3, Y1 + s * (a51 * q11 + a52 * q21 + a53 * q31 + a54 * q41),
                        Y2 + s * (a51 * q12 + a52 * q22 + a53 * q32 + a54 * q42),
                        Y3 + s * (a51 * q13 + a52 * q23 + a53 * q33 + a54 * q43), &q51, &q52, &q53);
                    rhs(P, R1, R3, Y1 + s * (a61 * q11 + a62 * q21 + a63 * q31 + a64 * q41 + a65 * q51),
                        Y2 + s * (a61 * q12 + a62 * q22 + a63 * q32 + a64 * q42 + a65 * q52),
                        Y3 + s * (a61 * q13 + a62 * q23 + a63 * q33 + a64 * q43 + a65 * q53), &q61, &q62, &q63);
                    const double z1 = Y1 + s * (a71 * q11 + a73 * q31 + a74 * q41 + a75 * q51 + a76 * q61);
                    const double z2 = Y2 + s * (a71 * q12 + a73 * q32 + a74 * q42 + a75 * q52 + a76 * q62);
                    const double z3 = Y3 + s * (a71 * q13 + a73 * q33 + a74 * q43 + a75 * q53 + a76 * q63);
                    rhs(P, R1, R3, z1, z2, z3, &q71, &q72, &q73);
                    const double d1 = s * (e1 * q11 + e3 * q31 + e4 * q41 + e5 * q51 + e6 * q61 + e7 * q71)
                                      / (atol + rtol * fmax(fabs(Y1), fabs(z1)));
                    const double d2 = s * (e1 * q12 + e3 * q32 + e4 * q42 + e5 * q52 + e6 * q62 + e7 * q72)
                                      / (atol + rtol * fmax(fabs(Y2), fabs(z2)));
                    const double d3 = s * (e1 * q13 + e3 * q33 + e4 * q43 + e5 * q53 + e6 * q63 + e7 * q73)
                                      / (atol + rtol * fmax(fabs(Y3), fabs(z3)));
                    const double err = fmax(sqrt((d1 * d1 + d2 * d2 + d3 * d3) / 3.0), 1e-10);
                    const int ok = moving & (err <= 1.0);
                    const double log_err = log(err); /* err^-alpha err_previous^beta as one exp and one log */
                    const double raw = safety * exp(-alpha * log_err + (ok ? beta * log_previous : 0.0));
                    const double clipped = fmin(max_factor, fmax(min_factor, rejected_before > 0.0 ? fmin(raw, 1.0) : raw));
                    const double factor = ok ? clipped : fmax(min_factor, raw);
                    const int landed = s >= remaining;
                    const double new_time = ok ? (landed ? target : T + s) : T;
                    h[l] = moving ? (ok ? fmax(s * factor, landed ? H : 0.0) : s * factor) : H;
                    time[l] = new_time;
                    previous[l] = ok ? fmax(log_err, log_first) : log_previous;
                    rejected_last[l] = moving ? (ok ? 0.0 : 1.0) : rejected_before;
                    accepted[l] += ok ? 1.0 : 0.0;
                    rejected[l] += (moving & !ok) ? 1.0 : 0.0;
                    y1[l] = ok ? z1 : Y1; y2[l] = ok ? z2 : Y2; y3[l] = ok ? z3 : Y3;
                    k1[l] = ok ? q71 : q11; k2[l] = ok ? q72 : q12; k3[l] = ok ? q73 : q13;
                    left += new_time < target;
                }
            }
        }
        for (int l = 0; l < BS; l++) {
            long j = b * BS + l;
            w[j] = y1[l]; w[M + j] = y2[l]; w[2 * M + j] = y3[l];
            counts[j] = accepted[l]; counts[M + j] = rejected[l]; counts[2 * M + j] = block_steps;
        }
    }
}
