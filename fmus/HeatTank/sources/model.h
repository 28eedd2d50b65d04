/*
 * HeatTank -- equations of an electric water heater (a 10 L tank with an immersion element)
 * started cold by switching on its supply.
 *
 * This header and model.c are the single place where the model is defined; the FMI glue
 * (fmi2.c) and the co-simulation integrator (cs.c) only call ht_rhs() and the small functions
 * below.  See docs/heattank.md for the equations, constants and tuning.
 */
#ifndef HEATTANK_MODEL_H
#define HEATTANK_MODEL_H

#define HT_NX 3          /* continuous states: element temperature, water temperature, sensor lag */
#define HT_NP 8          /* parameters exposed in the model description */

/* value references (must match modelDescription.xml) */
enum {
    VR_ELEMENT_R = 0, VR_ELEMENT_HA, VR_INSULATION_UA, VR_SENSOR_TAU, VR_SENSOR_OFFSET,
    VR_SUPPLY_RATIO, VR_INLET_FLOW, VR_SUPPLY_DELAY,       /* 0..7 parameters */
    VR_SENSOR_T = 10, VR_WATER_T, VR_ELEMENT_T, VR_HEATER_I, VR_HEATER_P,
    VR_CUTOUT,                                             /* 10..15 outputs */
    VR_X0 = 20,                                            /* 20..22 states */
    VR_DX0 = 24,                                           /* 24..26 derivatives */
    VR_SUPPLY_V = 30, VR_ELEMENT_Q, VR_LOSS_Q              /* 30..32 diagnostics */
};

enum { X_TE = 0, X_TW = 1, X_Y = 2 };

/* element thermal fuse: the element counts as burnt out once its temperature exceeds
   HT_CUTOUT_TEMP (checked after every accepted integration step, latched) */
#define HT_CUTOUT_TEMP 250.0     /* degC */

/* ambient (and initial) temperature */
#define HT_T_AMB 20.0            /* degC */

/* defaults of the parameters, indexed by value reference 0..7 */
extern const double ht_param_default[HT_NP];

/* nominal magnitudes of the states, used for absolute tolerances and ME nominals */
extern const double ht_x_nominal[HT_NX];

/* initial state (every temperature at ambient) */
void ht_initial_state(double *x);

typedef struct {
    double v;        /* supply voltage (V) */
    double i;        /* heater current (A) */
    double p;        /* electrical power V^2/R (W) */
    double q;        /* heat flow element -> water hA (Te - Tw) (W) */
    double loss;     /* heat lost by the water: insulation + cold inlet flow (W) */
} ht_aux_t;

/* 1 when the supply is on at time t (t >= supply.delay) */
int ht_supply_on(const double *p, double t);

/* Right-hand side dx/dt at (t, x) with the supply switched on (on != 0) or off.
   aux may be NULL. */
void ht_rhs(const double *p, double t, const double *x, int on, double *dx, ht_aux_t *aux);

/* The temperature sensor's reading for state x. */
double ht_sensor(const double *p, const double *x);

/* 1 when the element of state x is over the thermal fuse's temperature. */
int ht_over_temperature(const double *x);

/* Time points (> 0) where the solution is not smooth, sorted: supply.delay (when > 0).
   Returns their number (<= 1). */
int ht_breakpoints(const double *p, double *bp);

#endif
