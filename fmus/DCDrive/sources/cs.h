/*
 * DCDrive -- the simulation state and the co-simulation integrator shared by the FMI 2.0
 * (fmi2.c) and FMI 3.0 (fmus/DCDrive3/sources/fmi3.c) glue: an adaptive Dormand-Prince 5(4)
 * scheme (FSAL, rtol 1e-10) that lands exactly on communication points and on the model's
 * breakpoints (supply switched on at supply.delay, stall check one second later).
 */
#ifndef DCDRIVE_CS_H
#define DCDRIVE_CS_H

#include <stddef.h>
#include "model.h"

typedef struct {
    double p[DCD_NP];  /* parameters, by value reference */
    double x[DCD_NX];  /* continuous states */
    double t;          /* time (s) */
    int on;            /* supply switched on */
    int checked;       /* the stall check has been made */
    int stalled;       /* latched stall flag */
    double h;          /* proposed internal step size, 0 = not yet known */
} dcd_sim_t;

/* Parameters to their defaults, states to rest, t = 0, flags cleared. */
void dcd_sim_reset(dcd_sim_t *s);

/* Discrete updates at time s->t: supply switch and the one-off stall check. */
void dcd_sim_update_discrete(dcd_sim_t *s);

/* Integrate from s->t to tend (>= s->t), stopping exactly at each breakpoint on the way
   for the discrete updates.  Returns 0, or -1 with a one-line reason in msg. */
int dcd_sim_advance(dcd_sim_t *s, double tend, char *msg, size_t msglen);

#endif
