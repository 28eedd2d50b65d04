/*
 * HeatTank equations.  Every constant carries its unit; docs/heattank.md lists them.
 *
 *   Ce dTe/dt = P(t) - hA (Te - Tw)
 *   Cw dTw/dt = hA (Te - Tw) - UA (Tw - T_amb) - m_in cp (Tw - T_in)
 *   tau dy/dt = Tw - y                    (sensor lag, only when tau > 0)
 *   sensor.T  = (tau > 0 ? y : Tw) + offset
 *   P(t) = (ratio V_NOM)^2 / R,  I = ratio V_NOM / R   for t >= delay, else 0
 */
#include <math.h>
#include "model.h"

/* ---- fixed constants of the heater type ---- */
#define V_NOM   230.0            /* V, nominal supply voltage */
#define C_ELEM  4000.0           /* J/K, element, sheath and brass flange */
#define C_WATER 44000.0          /* J/K, 10 L of water (41.9 kJ/K) and the inner tank */
#define CP_W    4186.0           /* J/(kg.K), specific heat of water */
#define T_IN    10.0             /* degC, cold mains water entering with inlet.flow */

const double ht_param_default[HT_NP] = {
    26.45,   /* element.R       Ohm  (degradation input 1): 2000 W at 230 V */
    100.0,   /* element.hA      W/K  (degradation input 2): clean element */
    1.5,     /* insulation.UA   W/K  (degradation input 3): intact insulation */
    0.0,     /* sensor.tau      s    */
    0.0,     /* sensor.offset   K    */
    1.0,     /* supply.ratio    1    */
    0.0,     /* inlet.flow      kg/s */
    0.0,     /* supply.delay    s    */
};

const double ht_x_nominal[HT_NX] = { 100.0, 50.0, 50.0 };

void ht_initial_state(double *x)
{
    x[X_TE] = HT_T_AMB;
    x[X_TW] = HT_T_AMB;
    x[X_Y] = HT_T_AMB;
}

int ht_supply_on(const double *p, double t)
{
    return t >= p[VR_SUPPLY_DELAY];
}

void ht_rhs(const double *p, double t, const double *x, int on, double *dx, ht_aux_t *aux)
{
    (void)t;
    const double te = x[X_TE], tw = x[X_TW], y = x[X_Y];
    const double v = on ? p[VR_SUPPLY_RATIO] * V_NOM : 0.0;
    const double r = p[VR_ELEMENT_R];
    const double i = v / r;
    const double pw = v * i;
    const double q = p[VR_ELEMENT_HA] * (te - tw);
    const double loss = p[VR_INSULATION_UA] * (tw - HT_T_AMB)
                        + p[VR_INLET_FLOW] * CP_W * (tw - T_IN);
    const double tau = p[VR_SENSOR_TAU];
    dx[X_TE] = (pw - q) / C_ELEM;
    dx[X_TW] = (q - loss) / C_WATER;
    dx[X_Y] = tau > 0.0 ? (tw - y) / tau : 0.0;
    if (aux) {
        aux->v = v;
        aux->i = i;
        aux->p = pw;
        aux->q = q;
        aux->loss = loss;
    }
}

double ht_sensor(const double *p, const double *x)
{
    return (p[VR_SENSOR_TAU] > 0.0 ? x[X_Y] : x[X_TW]) + p[VR_SENSOR_OFFSET];
}

int ht_over_temperature(const double *x)
{
    return x[X_TE] > HT_CUTOUT_TEMP;
}

int ht_breakpoints(const double *p, double *bp)
{
    int n = 0;
    if (p[VR_SUPPLY_DELAY] > 0.0) bp[n++] = p[VR_SUPPLY_DELAY];
    return n;
}
