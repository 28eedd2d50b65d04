/*
 * PumpCircuit equations.  Every constant carries its unit; docs/model.md lists them.
 */
#include <math.h>
#include "model.h"

/* ---- fixed physical constants (ThermoSysPro defaults, DESIGN.md section 2) ---- */
#define UALIM   380.0            /* V, nominal supply voltage */
#define VROT    1400.0           /* rpm, nominal speed */
#define LM      1.0              /* H, motor inductance */
#define RM      1e-5             /* Ohm, motor resistance */
#define KI      1.0              /* N.m/A, torque constant */
#define JM      4.0              /* kg.m2, motor inertia */
#define JP      10.0             /* kg.m2, pump inertia */
#define A1      (-88.67)         /* s2/m5, head curve */
#define A2      0.0              /* s/m2, head curve */
#define A3      43.15            /* m, head curve */
#define B1      (-3.7751)        /* s2/m6, efficiency curve */
#define B3      (-0.0075464)     /* 1, efficiency curve */
#define RHMIN   0.05             /* 1, efficiency floor */
#define CF0     10.0             /* N.m, friction torque at rest */
#define RHO     998.0            /* kg/m3 */
#define G       9.80665          /* m/s2 */
#define LPIPE   10.0             /* m, pipe length */
#define DPIPE   0.2              /* m, pipe diameter */
#define LAMBDA  0.03             /* 1, friction factor */
#define KVALVE  1.733e12         /* valve equation constant (ThermoSysPro ControlValve) */
#define CVMAX   8005.42          /* valve Cv at full opening */
#define WEPS    1e-3             /* rad/s, regularisation of the hydraulic torque at standstill */

#define PI      3.14159265358979323846
#define WN      (VROT * PI / 30.0)                  /* rad/s */
#define KM      (30.0 * UALIM / (PI * VROT))        /* V.s/rad */
#define APIPE   (PI * DPIPE * DPIPE / 4.0)          /* m2 */

const double pc_param_default[PC_NP] = {
    10.0,    /* motor.D            N.m.s/rad */
    3.61,    /* pump.b2            s/m3      */
    0.0,     /* sensor.tau         s         */
    1.0,     /* sensor.gain        1         */
    0.0,     /* valve.opening_time s         */
    0.0,     /* pipe.fouling       1         */
    0.0,     /* pump.leak          m3/(s.Pa^0.5) */
    0.0,     /* motor.start_delay  s         */
    1.0,     /* motor.supply_ratio 1         */
    0.16425, /* valve.opening      1 (tuned: healthy nominal flow 400 kg/s) */
};

const double pc_x_nominal[PC_NX] = { 150.0, 1000.0, 400.0, 400.0 };

static double pump_dp(double qi, double R)
{
    return RHO * G * (A1 * qi * fabs(qi) + A2 * qi * R + A3 * R * fabs(R));
}

/* Impeller volume flow qi = Q/rho + leak*sqrt(max(dp(qi), 0)).
   dp is non-increasing in qi (a1 < 0, a2 = 0), so f(qi) = qi - Q/rho - leak*sqrt(dp+)
   is strictly increasing: the root is unique and bracketed by [Q/rho, Q/rho + leak*sqrt(dp+(Q/rho))].
   Safeguarded Newton to machine precision. */
static double impeller_flow(double Q, double R, double leak)
{
    const double q0 = Q / RHO;
    if (leak == 0.0) return q0;
    double dp0 = pump_dp(q0, R);
    if (dp0 <= 0.0) return q0;
    double lo = q0, hi = q0 + leak * sqrt(dp0);
    double q = hi;
    for (int it = 0; it < 100; ++it) {
        double dp = pump_dp(q, R);
        double s = dp > 0.0 ? sqrt(dp) : 0.0;
        double f = q - q0 - leak * s;
        if (f == 0.0) return q;
        if (f > 0.0) hi = q; else lo = q;
        double dfdq = 1.0;
        if (dp > 0.0) {
            double ddp = RHO * G * (2.0 * A1 * fabs(q) + A2 * R);
            dfdq = 1.0 - leak * ddp / (2.0 * s);
        }
        double qn = q - f / dfdq;
        if (!(qn > lo && qn < hi)) qn = 0.5 * (lo + hi);
        if (fabs(qn - q) <= 2e-16 * fabs(qn) || qn == lo || qn == hi) return qn;
        q = qn;
    }
    return q;
}

void pc_aux(const double *p, double t, const double *x, pc_aux_t *a)
{
    const double w = x[X_W];
    const double R = w / WN;
    const double qi = impeller_flow(x[X_Q], R, p[VR_PUMP_LEAK]);
    const double hn = A1 * qi * fabs(qi) + A2 * qi * R + A3 * R * fabs(R);
    double rh_raw;
    if (fabs(R) < 1e-6) {
        rh_raw = B3;                       /* guard: qi/R treated as 0 at standstill */
    } else {
        const double r = qi / R;
        rh_raw = (B1 * r + p[VR_PUMP_B2]) * r + B3;
    }
    const double rh = rh_raw > RHMIN ? rh_raw : RHMIN;
    a->R = R;
    a->qi = qi;
    a->hn = hn;
    a->dp = RHO * G * hn;
    a->rh_raw = rh_raw;
    a->rh = rh;
    /* Ch = rho*g*qi*hn/(rh*w) is singular at w = 0 (hydraulic power over speed); near
       standstill with a small residual flow it makes the equations infinitely stiff.
       Regularised as w/(w^2 + WEPS^2): relative change < 1e-6 for |w| > 1 rad/s. */
    a->Ch = RHO * G * qi * hn * w / (rh * (w * w + WEPS * WEPS));
    const double T = p[VR_VALVE_OPENING_TIME];
    double op = p[VR_VALVE_OPENING];
    if (T > 0.0) {
        double f = t / T;
        if (f > 1.0) f = 1.0;
        if (f < 0.01) f = 0.01;             /* the valve is never fully shut */
        op *= f;
    }
    a->opening = op;
}

void pc_rhs(const double *p, double t, const double *x, int motor_on, double *dx, pc_aux_t *aux)
{
    pc_aux_t local;
    pc_aux_t *a = aux ? aux : &local;
    pc_aux(p, t, x, a);

    const double w = x[X_W], I = x[X_I], Q = x[X_Q], y = x[X_Y];
    const double aR = fabs(a->R);
    const double Cf = aR < 1.0 ? CF0 * (1.0 - aR) : 0.0;
    const double Um = motor_on ? p[VR_MOTOR_SUPPLY_RATIO] * UALIM : 0.0;
    const double kf = 1.0 + p[VR_PIPE_FOULING];
    const double Cv = a->opening * CVMAX;
    const double QQ = Q * fabs(Q);
    const double dP_pipe = kf * LAMBDA * LPIPE / DPIPE * QQ / (2.0 * APIPE * APIPE * RHO);
    const double dP_valve = kf * KVALVE * QQ / (RHO * RHO * Cv * Cv);
    const double tau = p[VR_SENSOR_TAU];

    dx[X_W] = (KI * I - p[VR_MOTOR_D] * w - a->Ch - Cf) / (JM + JP);
    dx[X_I] = (Um - KM * w - RM * I) / LM;
    dx[X_Q] = (a->dp - dP_pipe - dP_valve) * (APIPE / LPIPE);
    dx[X_Y] = tau > 0.0 ? (Q - y) / tau : 0.0;
}

int pc_nonphysical_now(const double *p, const pc_aux_t *a)
{
    if (!(a->R > 0.1)) return 0;
    if (!(a->rh_raw <= RHMIN)) return 0;
    const double r = a->qi / a->R;
    return r > p[VR_PUMP_B2] / (2.0 * fabs(B1));
}

int pc_breakpoints(const double *p, double *bp)
{
    double c[3];
    int n = 0;
    if (p[VR_MOTOR_START_DELAY] > 0.0) c[n++] = p[VR_MOTOR_START_DELAY];
    if (p[VR_VALVE_OPENING_TIME] > 0.0) {
        c[n++] = 0.01 * p[VR_VALVE_OPENING_TIME];
        c[n++] = p[VR_VALVE_OPENING_TIME];
    }
    /* insertion sort */
    for (int i = 1; i < n; ++i) {
        double v = c[i]; int j = i - 1;
        while (j >= 0 && c[j] > v) { c[j + 1] = c[j]; --j; }
        c[j + 1] = v;
    }
    for (int i = 0; i < n; ++i) bp[i] = c[i];
    return n;
}
