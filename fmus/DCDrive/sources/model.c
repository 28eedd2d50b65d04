/*
 * DCDrive equations.  Every constant carries its unit; docs/dcdrive.md lists them.
 *
 *   L di/dt = V(t) - R i - Ke w
 *   J dw/dt = Kt i - b w - c w^2 - (Tc + extra) tanh(w / w_c)
 *   tau dy/dt = w - y              (tachometer lag, only when tau > 0)
 *   tacho.w = gain * (tau > 0 ? y : w)
 *   V(t) = ratio * V_NOM for t >= delay, else 0
 */
#include <math.h>
#include "model.h"

/* ---- fixed constants of the drive type ---- */
#define V_NOM   48.0             /* V, nominal supply voltage */
#define KE      0.1              /* V.s/rad, back-EMF constant */
#define KT      0.1              /* N.m/A, torque constant (= KE in SI units) */
#define L_ARM   5e-3             /* H, armature inductance (L/R = 5 ms at R = 1 Ohm) */
#define J_TOT   5e-3             /* kg.m2, rotor + fan inertia */
#define TC      1.0              /* N.m, Coulomb friction of bearing seals and brushes */
#define W_C     0.5              /* rad/s, regularisation speed of the Coulomb friction */

const double dcd_param_default[DCD_NP] = {
    1e-3,    /* bearing.b     N.m.s/rad  (degradation input 1) */
    1.0,     /* winding.R     Ohm        (degradation input 2) */
    0.0,     /* tacho.tau     s          */
    1.0,     /* tacho.gain    1          */
    1.0,     /* supply.ratio  1          */
    0.0,     /* load.extra    N.m        */
    0.0,     /* supply.delay  s          */
    7e-6,    /* fan.c         N.m.s2/rad2 (constant of the unit type) */
};

const double dcd_x_nominal[DCD_NX] = { 10.0, 300.0, 300.0 };

int dcd_supply_on(const double *p, double t)
{
    return t >= p[VR_SUPPLY_DELAY];
}

void dcd_rhs(const double *p, double t, const double *x, int on, double *dx, dcd_aux_t *aux)
{
    (void)t;
    const double i = x[X_I], w = x[X_W], y = x[X_Y];
    const double v = on ? p[VR_SUPPLY_RATIO] * V_NOM : 0.0;
    const double emf = KE * w;
    const double torque = KT * i;
    const double load = p[VR_BEARING_B] * w + p[VR_FAN_C] * w * fabs(w)
                        + (TC + p[VR_LOAD_EXTRA]) * tanh(w / W_C);
    const double tau = p[VR_TACHO_TAU];
    dx[X_I] = (v - p[VR_WINDING_R] * i - emf) / L_ARM;
    dx[X_W] = (torque - load) / J_TOT;
    dx[X_Y] = tau > 0.0 ? (w - y) / tau : 0.0;
    if (aux) {
        aux->v = v;
        aux->emf = emf;
        aux->torque = torque;
        aux->load = load;
    }
}

double dcd_tacho(const double *p, const double *x)
{
    return p[VR_TACHO_GAIN] * (p[VR_TACHO_TAU] > 0.0 ? x[X_Y] : x[X_W]);
}

double dcd_stall_check_time(const double *p)
{
    const double d = p[VR_SUPPLY_DELAY];
    return (d > 0.0 ? d : 0.0) + DCD_STALL_CHECK;
}

int dcd_stalled_now(const double *x)
{
    return !(x[X_W] >= DCD_STALL_SPEED);
}

int dcd_breakpoints(const double *p, double *bp)
{
    int n = 0;
    if (p[VR_SUPPLY_DELAY] > 0.0) bp[n++] = p[VR_SUPPLY_DELAY];
    bp[n++] = dcd_stall_check_time(p);
    return n;
}
