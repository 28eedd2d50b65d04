/*
 * HeatTank -- the simulation state and the co-simulation integrator used by the FMI 2.0
 * glue (fmi2.c): an adaptive Dormand-Prince 5(4) scheme (FSAL, rtol 1e-10) that lands
 * exactly on communication points and on the model's breakpoint (supply switched on at
 * supply.delay).  The element's thermal fuse is checked after every accepted step.
 */
#ifndef HEATTANK_CS_H
#define HEATTANK_CS_H

#include <stddef.h>
#include "model.h"

typedef struct {
    double p[HT_NP];   /* parameters, by value reference */
    double x[HT_NX];   /* continuous states */
    double t;          /* time (s) */
    int on;            /* supply switched on */
    int cutout;        /* latched thermal-fuse flag */
    double h;          /* proposed internal step size, 0 = not yet known */
} ht_sim_t;

/* Parameters to their defaults, temperatures to ambient, t = 0, flags cleared. */
void ht_sim_reset(ht_sim_t *s);

/* Discrete updates at time s->t: supply switch and the thermal fuse. */
void ht_sim_update_discrete(ht_sim_t *s);

/* Integrate from s->t to tend (>= s->t), stopping exactly at the breakpoint on the way
   for the discrete updates.  Returns 0, or -1 with a one-line reason in msg. */
int ht_sim_advance(ht_sim_t *s, double tend, char *msg, size_t msglen);

#endif
