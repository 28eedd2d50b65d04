/*
 * DCDrive -- equations of a permanent-magnet DC motor started by a voltage step and driving
 * a fan-like load.
 *
 * This header and model.c are the single place where the model is defined; the FMI glue
 * (fmi2.c in fmus/DCDrive, fmi3.c in fmus/DCDrive3, which links to these two files) and the
 * co-simulation integrator only call dcd_rhs() and the small helpers below.  See
 * docs/dcdrive.md for the equations, constants and tuning.
 */
#ifndef DCDRIVE_MODEL_H
#define DCDRIVE_MODEL_H

#define DCD_NX 3         /* continuous states: armature current, shaft speed, tacho lag output */
#define DCD_NP 8         /* parameters exposed in the model descriptions */

/* value references (must match both modelDescription.xml files) */
enum {
    VR_BEARING_B = 0, VR_WINDING_R, VR_TACHO_TAU, VR_TACHO_GAIN, VR_SUPPLY_RATIO,
    VR_LOAD_EXTRA, VR_SUPPLY_DELAY, VR_FAN_C,          /* 0..7 parameters */
    VR_TACHO_W = 10, VR_SHAFT_W, VR_ARMATURE_I, VR_SHAFT_TORQUE,
    VR_STALLED,                                        /* 10..14 outputs */
    VR_X0 = 20,                                        /* 20..22 states */
    VR_DX0 = 24,                                       /* 24..26 derivatives */
    VR_SUPPLY_V = 30, VR_MOTOR_EMF, VR_LOAD_TORQUE,    /* 30..32 diagnostics */
    VR_TIME = 40                                       /* FMI 3 independent variable */
};

enum { X_I = 0, X_W = 1, X_Y = 2 };

/* stall protection: the drive counts as stalled when, DCD_STALL_CHECK seconds after the
   supply is switched on, the shaft turns slower than DCD_STALL_SPEED */
#define DCD_STALL_CHECK 1.0      /* s */
#define DCD_STALL_SPEED 48.0     /* rad/s, 10 % of the nominal no-load speed */

/* defaults of the parameters, indexed by value reference 0..7 */
extern const double dcd_param_default[DCD_NP];

/* nominal magnitudes of the states, used for absolute tolerances and ME nominals */
extern const double dcd_x_nominal[DCD_NX];

typedef struct {
    double v;        /* armature supply voltage (V) */
    double emf;      /* back-EMF Ke*w (V) */
    double torque;   /* electromagnetic torque Kt*i (N.m) */
    double load;     /* total load torque b*w + c*w^2 + (Tc + extra)*tanh(w/w_c) (N.m) */
} dcd_aux_t;

/* 1 when the supply is on at time t (t >= supply.delay) */
int dcd_supply_on(const double *p, double t);

/* Right-hand side dx/dt at (t, x) with the supply switched on (on != 0) or off.
   aux may be NULL. */
void dcd_rhs(const double *p, double t, const double *x, int on, double *dx, dcd_aux_t *aux);

/* The tachometer reading for state x. */
double dcd_tacho(const double *p, const double *x);

/* Time of the stall check: supply.delay + DCD_STALL_CHECK. */
double dcd_stall_check_time(const double *p);

/* 1 when the shaft speed of state x is below the stall speed (to be evaluated at the
   stall check time only). */
int dcd_stalled_now(const double *x);

/* Time points (> 0) where the solution is not smooth or a discrete check happens, sorted:
   supply.delay (when > 0) and the stall check time.  Returns their number (<= 2). */
int dcd_breakpoints(const double *p, double *bp);

#endif
