/*
 * PumpCircuit -- equations of the cooling loop (motor -> pump -> pipe -> valve -> tank).
 *
 * This header is the single place where the model is defined; the FMI glue (fmi2.c) and
 * the co-simulation integrator only call pc_rhs() and pc_aux().  See docs/model.md and
 * DESIGN.md section 2 for the equations.
 */
#ifndef PUMPCIRCUIT_MODEL_H
#define PUMPCIRCUIT_MODEL_H

#define PC_NX 4          /* continuous states: w, I, Q, y */
#define PC_NP 10         /* parameters exposed in modelDescription.xml */

/* value references (must match modelDescription.xml) */
enum {
    VR_MOTOR_D = 0, VR_PUMP_B2, VR_SENSOR_TAU, VR_SENSOR_GAIN, VR_VALVE_OPENING_TIME,
    VR_PIPE_FOULING, VR_PUMP_LEAK, VR_MOTOR_START_DELAY, VR_MOTOR_SUPPLY_RATIO,
    VR_VALVE_OPENING,                                  /* 0..9 parameters */
    VR_SENSOR_M_FLOW = 10, VR_PUMP_M_FLOW, VR_MOTOR_W, VR_PUMP_DP, VR_MOTOR_I,
    VR_NONPHYSICAL,                                    /* 10..15 outputs */
    VR_X0 = 20,                                        /* 20..23 states */
    VR_DX0 = 24,                                       /* 24..27 derivatives */
    VR_PUMP_QI = 30, VR_PUMP_RH, VR_MOTOR_CH, VR_VALVE_OPENING_EFF  /* 30..33 diagnostics */
};

enum { X_W = 0, X_I = 1, X_Q = 2, X_Y = 3 };

/* defaults of the parameters, indexed by value reference 0..9 */
extern const double pc_param_default[PC_NP];

/* nominal magnitudes of the states, used for absolute tolerances and ME nominals */
extern const double pc_x_nominal[PC_NX];

typedef struct {
    double R;        /* relative speed w/wn (1) */
    double qi;       /* impeller volume flow (m3/s) */
    double hn;       /* pump head (m) */
    double dp;       /* pump pressure rise (Pa) */
    double rh_raw;   /* efficiency polynomial before the floor (1); = b3 when |R| < 1e-6 */
    double rh;       /* efficiency after the floor (1) */
    double Ch;       /* hydraulic torque (N.m) */
    double opening;  /* effective valve opening (1) */
} pc_aux_t;

/* Right-hand side dx/dt at (t, x) with the supply switched on (motor_on != 0) or off.
   aux may be NULL. */
void pc_rhs(const double *p, double t, const double *x, int motor_on, double *dx, pc_aux_t *aux);

/* Algebraic quantities only (no derivatives). */
void pc_aux(const double *p, double t, const double *x, pc_aux_t *aux);

/* 1 when the pump sits at its efficiency floor on the high-flow branch while R > 0.1. */
int pc_nonphysical_now(const double *p, const pc_aux_t *aux);

/* Time points (> 0) where the right-hand side is discontinuous or kinked by design:
   start_delay, 0.01*opening_time, opening_time.  Returns their number (<= 3), sorted. */
int pc_breakpoints(const double *p, double *bp);

#endif
