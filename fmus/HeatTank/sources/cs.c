/*
 * HeatTank co-simulation integrator (see cs.h): Dormand-Prince 5(4) with FSAL, error norm
 * rtol*|x| + atol_rel*nominal per state, step-size proposal kept across doStep calls.
 */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "cs.h"

#define CS_RTOL       1e-10
#define CS_ATOL_REL   1e-10          /* atol_i = CS_ATOL_REL * nominal_i */
#define CS_MAX_STEPS  200000L        /* internal steps (accepted + rejected) per advance */
#define CS_H_INIT     1e-2           /* s; the element warms with a time constant of 40 s */

static const double
    c2 = 1.0 / 5, c3 = 3.0 / 10, c4 = 4.0 / 5, c5 = 8.0 / 9,
    a21 = 1.0 / 5,
    a31 = 3.0 / 40, a32 = 9.0 / 40,
    a41 = 44.0 / 45, a42 = -56.0 / 15, a43 = 32.0 / 9,
    a51 = 19372.0 / 6561, a52 = -25360.0 / 2187, a53 = 64448.0 / 6561, a54 = -212.0 / 729,
    a61 = 9017.0 / 3168, a62 = -355.0 / 33, a63 = 46732.0 / 5247, a64 = 49.0 / 176,
    a65 = -5103.0 / 18656,
    a71 = 35.0 / 384, a73 = 500.0 / 1113, a74 = 125.0 / 192, a75 = -2187.0 / 6784,
    a76 = 11.0 / 84,
    e1 = 71.0 / 57600, e3 = -71.0 / 16695, e4 = 71.0 / 1920, e5 = -17253.0 / 339200,
    e6 = 22.0 / 525, e7 = -1.0 / 40;

void ht_sim_reset(ht_sim_t *s)
{
    memcpy(s->p, ht_param_default, sizeof s->p);
    ht_initial_state(s->x);
    s->t = 0.0;
    s->on = 0;
    s->cutout = 0;
    s->h = 0.0;
}

void ht_sim_update_discrete(ht_sim_t *s)
{
    s->on = ht_supply_on(s->p, s->t);
    if (ht_over_temperature(s->x)) s->cutout = 1;
}

static int all_finite(const double *x, int n)
{
    for (int i = 0; i < n; ++i) if (!isfinite(x[i])) return 0;
    return 1;
}

/* integrate from s->t to tb (> s->t) with constant discrete state; lands exactly on tb */
static int integrate_segment(ht_sim_t *s, double tb, long *nsteps, char *msg, size_t msglen)
{
    const int n = HT_NX;
    double k1[HT_NX], k2[HT_NX], k3[HT_NX], k4[HT_NX], k5[HT_NX], k6[HT_NX], k7[HT_NX];
    double xs[HT_NX], xn[HT_NX];
    const double *p = s->p;
    const int on = s->on;

    ht_rhs(p, s->t, s->x, on, k1, NULL);
    if (s->h <= 0.0) s->h = CS_H_INIT;

    while (s->t < tb) {
        if (++*nsteps > CS_MAX_STEPS) {
            snprintf(msg, msglen, "HeatTank: more than %ld internal steps in one doStep at t=%g (h=%g)",
                     CS_MAX_STEPS, s->t, s->h);
            return -1;
        }
        const double t = s->t, dist = tb - t;
        double h = s->h;
        int last = 0;
        if (t + 1.1 * h >= tb) { h = dist; last = 1; }
        if (h < 1e-14 * (fabs(t) + 1.0) && !last) {
            snprintf(msg, msglen, "HeatTank: step size underflow (h=%g) at t=%g", h, t);
            return -1;
        }
        int i;
        for (i = 0; i < n; ++i) xs[i] = s->x[i] + h * a21 * k1[i];
        ht_rhs(p, t + c2 * h, xs, on, k2, NULL);
        for (i = 0; i < n; ++i) xs[i] = s->x[i] + h * (a31 * k1[i] + a32 * k2[i]);
        ht_rhs(p, t + c3 * h, xs, on, k3, NULL);
        for (i = 0; i < n; ++i) xs[i] = s->x[i] + h * (a41 * k1[i] + a42 * k2[i] + a43 * k3[i]);
        ht_rhs(p, t + c4 * h, xs, on, k4, NULL);
        for (i = 0; i < n; ++i)
            xs[i] = s->x[i] + h * (a51 * k1[i] + a52 * k2[i] + a53 * k3[i] + a54 * k4[i]);
        ht_rhs(p, t + c5 * h, xs, on, k5, NULL);
        for (i = 0; i < n; ++i)
            xs[i] = s->x[i] + h * (a61 * k1[i] + a62 * k2[i] + a63 * k3[i] + a64 * k4[i]
                                   + a65 * k5[i]);
        const double tn = last ? tb : t + h;
        ht_rhs(p, tn, xs, on, k6, NULL);
        for (i = 0; i < n; ++i)
            xn[i] = s->x[i] + h * (a71 * k1[i] + a73 * k3[i] + a74 * k4[i] + a75 * k5[i]
                                   + a76 * k6[i]);
        ht_rhs(p, tn, xn, on, k7, NULL);

        double err = 0.0;
        for (i = 0; i < n; ++i) {
            const double e = h * (e1 * k1[i] + e3 * k3[i] + e4 * k4[i] + e5 * k5[i]
                                  + e6 * k6[i] + e7 * k7[i]);
            const double xa = fabs(s->x[i]), xb = fabs(xn[i]);
            const double sc = CS_ATOL_REL * ht_x_nominal[i] + CS_RTOL * (xa > xb ? xa : xb);
            err += (e / sc) * (e / sc);
        }
        err = sqrt(err / n);

        if (err <= 1.0) {
            double fac = err > 0.0 ? 0.9 * pow(err, -0.2) : 5.0;
            if (fac > 5.0) fac = 5.0;
            if (fac < 0.2) fac = 0.2;
            const double hnew = h * fac;
            /* a step shortened to land on tb says little about the step size the
               solution tolerates: keep the proposal unless it must shrink */
            /* nor does a sliver up to a breakpoint a rounding error away (1e-16 s):
               shrinking to it would leave the next step below the underflow floor */
            const int sliver = last && h < 1e-9 * (fabs(t) + 1.0);
            if (!sliver && (!last || h >= s->h || hnew < s->h)) s->h = hnew;
            s->t = tn;
            memcpy(s->x, xn, sizeof xn);
            memcpy(k1, k7, sizeof k7);
            if (ht_over_temperature(s->x)) s->cutout = 1;
            if (!all_finite(s->x, n)) {
                snprintf(msg, msglen, "HeatTank: non-finite state at t=%g (Te=%g Tw=%g)",
                         s->t, s->x[X_TE], s->x[X_TW]);
                return -1;
            }
        } else {
            double fac = isfinite(err) ? 0.9 * pow(err, -0.2) : 0.2;
            if (fac < 0.2) fac = 0.2;
            if (fac > 0.9) fac = 0.9;
            s->h = h * fac;
        }
    }
    return 0;
}

int ht_sim_advance(ht_sim_t *s, double tend, char *msg, size_t msglen)
{
    double bp[1];
    const int nb = ht_breakpoints(s->p, bp);
    long nsteps = 0;
    while (s->t < tend) {
        double tb = tend;
        for (int i = 0; i < nb; ++i)
            if (bp[i] > s->t && bp[i] < tb) { tb = bp[i]; break; }
        ht_sim_update_discrete(s);
        if (integrate_segment(s, tb, &nsteps, msg, msglen) != 0) return -1;
    }
    s->t = tend;
    ht_sim_update_discrete(s);
    return 0;
}
