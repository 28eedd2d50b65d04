/*
 * DCDrive -- FMI 2.0 glue: Model Exchange and Co-Simulation in one binary.
 *
 * Co-Simulation integrates the equations of model.c with an adaptive Dormand-Prince 5(4)
 * scheme (FSAL, rtol 1e-10) that lands exactly on communication points and on the model's
 * breakpoints (supply switched on at supply.delay, stall check one second later).
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "model.h"

#define CS_RTOL       1e-10
#define CS_ATOL_REL   1e-10          /* atol_i = CS_ATOL_REL * nominal_i */
#define CS_MAX_STEPS  200000L        /* internal steps (accepted + rejected) per doStep */
#define CS_H_INIT     1e-4

typedef enum { M_INSTANTIATED, M_INIT, M_EVENT, M_CONT, M_STEP, M_TERMINATED, M_ERROR } mode_t_;

typedef struct {
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    char name[256];
    fmi2Type type;
    int logging_on;
    mode_t_ mode;
    double p[DCD_NP];
    double x[DCD_NX];
    double t;
    int on;            /* supply switched on */
    int checked;       /* the stall check has been made */
    double stalled;    /* latched stall flag (0 or 1) */
    double h;          /* CS: proposed internal step size, 0 = not yet known */
} inst_t;

static void logmsg(inst_t *m, fmi2Status st, const char *cat, const char *fmt, ...)
{
    if (!m || !m->logger) return;
    if (st < fmi2Warning && !m->logging_on) return;
    char buf[512];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    for (char *c = buf; *c; ++c) if (*c == '%') *c = ' ';   /* message is used as a format */
    m->logger(m->env, m->name, st, cat, buf);
}

static void reset_values(inst_t *m)
{
    memcpy(m->p, dcd_param_default, sizeof m->p);
    memset(m->x, 0, sizeof m->x);
    m->t = 0.0;
    m->on = 0;
    m->checked = 0;
    m->stalled = 0.0;
    m->h = 0.0;
}

/* discrete updates at time m->t: supply switch and the one-off stall check */
static void update_discrete(inst_t *m)
{
    m->on = dcd_supply_on(m->p, m->t);
    if (!m->checked && m->t >= dcd_stall_check_time(m->p)) {
        m->checked = 1;
        if (dcd_stalled_now(m->x)) m->stalled = 1.0;
    }
}

static int all_finite(const double *x, int n)
{
    for (int i = 0; i < n; ++i) if (!isfinite(x[i])) return 0;
    return 1;
}

/* ------------------------------------------------------------------------------------ */
/* Co-Simulation integrator                                                               */

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

/* integrate from m->t to tb (> m->t) with constant discrete state; lands exactly on tb */
static fmi2Status integrate_segment(inst_t *m, double tb, long *nsteps)
{
    const int n = DCD_NX;
    double k1[DCD_NX], k2[DCD_NX], k3[DCD_NX], k4[DCD_NX], k5[DCD_NX], k6[DCD_NX], k7[DCD_NX];
    double xs[DCD_NX], xn[DCD_NX];
    const double *p = m->p;
    const int on = m->on;

    dcd_rhs(p, m->t, m->x, on, k1, NULL);
    if (m->h <= 0.0) m->h = CS_H_INIT;

    while (m->t < tb) {
        if (++*nsteps > CS_MAX_STEPS) {
            logmsg(m, fmi2Error, "logStatusError",
                   "DCDrive: more than %ld internal steps in one doStep at t=%g (h=%g)",
                   CS_MAX_STEPS, m->t, m->h);
            return fmi2Error;
        }
        const double t = m->t, dist = tb - t;
        double h = m->h;
        int last = 0;
        if (t + 1.1 * h >= tb) { h = dist; last = 1; }
        if (h < 1e-14 * (fabs(t) + 1.0) && !last) {
            logmsg(m, fmi2Error, "logStatusError",
                   "DCDrive: step size underflow (h=%g) at t=%g", h, t);
            return fmi2Error;
        }
        int i;
        for (i = 0; i < n; ++i) xs[i] = m->x[i] + h * a21 * k1[i];
        dcd_rhs(p, t + c2 * h, xs, on, k2, NULL);
        for (i = 0; i < n; ++i) xs[i] = m->x[i] + h * (a31 * k1[i] + a32 * k2[i]);
        dcd_rhs(p, t + c3 * h, xs, on, k3, NULL);
        for (i = 0; i < n; ++i) xs[i] = m->x[i] + h * (a41 * k1[i] + a42 * k2[i] + a43 * k3[i]);
        dcd_rhs(p, t + c4 * h, xs, on, k4, NULL);
        for (i = 0; i < n; ++i)
            xs[i] = m->x[i] + h * (a51 * k1[i] + a52 * k2[i] + a53 * k3[i] + a54 * k4[i]);
        dcd_rhs(p, t + c5 * h, xs, on, k5, NULL);
        for (i = 0; i < n; ++i)
            xs[i] = m->x[i] + h * (a61 * k1[i] + a62 * k2[i] + a63 * k3[i] + a64 * k4[i]
                                   + a65 * k5[i]);
        const double tn = last ? tb : t + h;
        dcd_rhs(p, tn, xs, on, k6, NULL);
        for (i = 0; i < n; ++i)
            xn[i] = m->x[i] + h * (a71 * k1[i] + a73 * k3[i] + a74 * k4[i] + a75 * k5[i]
                                   + a76 * k6[i]);
        dcd_rhs(p, tn, xn, on, k7, NULL);

        double err = 0.0;
        for (i = 0; i < n; ++i) {
            const double e = h * (e1 * k1[i] + e3 * k3[i] + e4 * k4[i] + e5 * k5[i]
                                  + e6 * k6[i] + e7 * k7[i]);
            const double xa = fabs(m->x[i]), xb = fabs(xn[i]);
            const double sc = CS_ATOL_REL * dcd_x_nominal[i] + CS_RTOL * (xa > xb ? xa : xb);
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
            if (!last || h >= m->h || hnew < m->h) m->h = hnew;
            m->t = tn;
            memcpy(m->x, xn, sizeof xn);
            memcpy(k1, k7, sizeof k7);
            if (!all_finite(m->x, n)) {
                logmsg(m, fmi2Error, "logStatusError",
                       "DCDrive: non-finite state at t=%g (i=%g w=%g)",
                       m->t, m->x[X_I], m->x[X_W]);
                return fmi2Error;
            }
        } else {
            double fac = isfinite(err) ? 0.9 * pow(err, -0.2) : 0.2;
            if (fac < 0.2) fac = 0.2;
            if (fac > 0.9) fac = 0.9;
            m->h = h * fac;
        }
    }
    return fmi2OK;
}

/* ------------------------------------------------------------------------------------ */
/* FMI 2.0 API                                                                            */

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[])
{
    (void)nCategories; (void)categories;
    if (!c) return fmi2Error;
    ((inst_t *)c)->logging_on = loggingOn ? 1 : 0;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation,
                              const fmi2CallbackFunctions *functions, fmi2Boolean visible,
                              fmi2Boolean loggingOn)
{
    (void)fmuGUID; (void)fmuResourceLocation; (void)visible;
    inst_t *m = (inst_t *)calloc(1, sizeof(inst_t));
    if (!m) return NULL;
    if (functions) { m->logger = functions->logger; m->env = functions->componentEnvironment; }
    snprintf(m->name, sizeof m->name, "%s", instanceName ? instanceName : "DCDrive");
    m->type = fmuType;
    m->logging_on = loggingOn ? 1 : 0;
    reset_values(m);
    m->mode = M_INSTANTIATED;
    return m;
}

void fmi2FreeInstance(fmi2Component c) { free(c); }

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined,
                               fmi2Real tolerance, fmi2Real startTime,
                               fmi2Boolean stopTimeDefined, fmi2Real stopTime)
{
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    inst_t *m = (inst_t *)c;
    if (!m || m->mode != M_INSTANTIATED) return fmi2Error;
    m->t = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c)
{
    inst_t *m = (inst_t *)c;
    if (!m || m->mode != M_INSTANTIATED) return fmi2Error;
    m->mode = M_INIT;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c)
{
    inst_t *m = (inst_t *)c;
    if (!m || m->mode != M_INIT) return fmi2Error;
    update_discrete(m);
    m->h = 0.0;
    m->mode = m->type == fmi2CoSimulation ? M_STEP : M_EVENT;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c)
{
    inst_t *m = (inst_t *)c;
    if (!m) return fmi2Error;
    m->mode = M_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c)
{
    inst_t *m = (inst_t *)c;
    if (!m) return fmi2Error;
    reset_values(m);
    m->mode = M_INSTANTIATED;
    return fmi2OK;
}

static int is_param(fmi2ValueReference v) { return v < DCD_NP; }

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[])
{
    inst_t *m = (inst_t *)c;
    if (!m) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    if (!vr || !value) return fmi2Error;
    double dx[DCD_NX];
    dcd_aux_t a;
    int have = 0;
    for (size_t k = 0; k < nvr; ++k) {
        const fmi2ValueReference v = vr[k];
        if (is_param(v)) { value[k] = m->p[v]; continue; }
        if (v >= VR_X0 && v < VR_X0 + DCD_NX) { value[k] = m->x[v - VR_X0]; continue; }
        switch (v) {
        case VR_TACHO_W: value[k] = dcd_tacho(m->p, m->x); continue;
        case VR_SHAFT_W: value[k] = m->x[X_W]; continue;
        case VR_ARMATURE_I: value[k] = m->x[X_I]; continue;
        case VR_STALLED: value[k] = m->stalled; continue;
        default: break;
        }
        if (!have) { dcd_rhs(m->p, m->t, m->x, m->on, dx, &a); have = 1; }
        switch (v) {
        case VR_SHAFT_TORQUE: value[k] = a.torque; break;
        case VR_SUPPLY_V: value[k] = a.v; break;
        case VR_MOTOR_EMF: value[k] = a.emf; break;
        case VR_LOAD_TORQUE: value[k] = a.load; break;
        default:
            if (v >= VR_DX0 && v < VR_DX0 + DCD_NX) { value[k] = dx[v - VR_DX0]; break; }
            logmsg(m, fmi2Error, "logStatusError", "DCDrive: unknown value reference %u",
                   (unsigned)v);
            return fmi2Error;
        }
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       const fmi2Real value[])
{
    inst_t *m = (inst_t *)c;
    if (!m) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    if (!vr || !value) return fmi2Error;
    const int before_init = m->mode == M_INSTANTIATED || m->mode == M_INIT;
    for (size_t k = 0; k < nvr; ++k) {
        const fmi2ValueReference v = vr[k];
        if ((is_param(v) || (v >= VR_X0 && v < VR_X0 + DCD_NX)) && before_init) {
            if (!isfinite(value[k])) {
                logmsg(m, fmi2Error, "logStatusError",
                       "DCDrive: non-finite value for value reference %u", (unsigned)v);
                return fmi2Error;
            }
            if (is_param(v)) m->p[v] = value[k]; else m->x[v - VR_X0] = value[k];
            continue;
        }
        logmsg(m, fmi2Error, "logStatusError",
               "DCDrive: value reference %u cannot be set in the current state", (unsigned)v);
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[])
{ (void)c; (void)vr; (void)value; return nvr == 0 ? fmi2OK : fmi2Error; }
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[])
{ (void)c; (void)vr; (void)value; return nvr == 0 ? fmi2OK : fmi2Error; }
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[])
{ (void)c; (void)vr; (void)value; return nvr == 0 ? fmi2OK : fmi2Error; }
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[])
{ (void)c; (void)vr; (void)value; return nvr == 0 ? fmi2OK : fmi2Error; }
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[])
{ (void)c; (void)vr; (void)value; return nvr == 0 ? fmi2OK : fmi2Error; }
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[])
{ (void)c; (void)vr; (void)value; return nvr == 0 ? fmi2OK : fmi2Error; }

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *size)
{ (void)c; (void)s; (void)size; return fmi2Error; }
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t size)
{ (void)c; (void)s; (void)b; (void)size; return fmi2Error; }
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t size, fmi2FMUstate *s)
{ (void)c; (void)b; (void)size; (void)s; return fmi2Error; }
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vU[], size_t nU,
                                        const fmi2ValueReference vK[], size_t nK,
                                        const fmi2Real dvK[], fmi2Real dvU[])
{ (void)c; (void)vU; (void)nU; (void)vK; (void)nK; (void)dvK; (void)dvU; return fmi2Error; }

/* ---- Model Exchange ---- */

fmi2Status fmi2EnterEventMode(fmi2Component c)
{
    inst_t *m = (inst_t *)c;
    if (!m || (m->mode != M_CONT && m->mode != M_EVENT)) return fmi2Error;
    m->mode = M_EVENT;
    return fmi2OK;
}

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *ei)
{
    inst_t *m = (inst_t *)c;
    if (!m || m->mode != M_EVENT || !ei) return fmi2Error;
    update_discrete(m);
    double bp[2];
    const int nb = dcd_breakpoints(m->p, bp);
    ei->newDiscreteStatesNeeded = fmi2False;
    ei->terminateSimulation = fmi2False;
    ei->nominalsOfContinuousStatesChanged = fmi2False;
    ei->valuesOfContinuousStatesChanged = fmi2False;
    ei->nextEventTimeDefined = fmi2False;
    ei->nextEventTime = 0.0;
    for (int i = 0; i < nb; ++i) {
        if (bp[i] > m->t) {
            ei->nextEventTimeDefined = fmi2True;
            ei->nextEventTime = bp[i];
            break;
        }
    }
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c)
{
    inst_t *m = (inst_t *)c;
    if (!m || m->mode != M_EVENT) return fmi2Error;
    m->mode = M_CONT;
    return fmi2OK;
}

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi2Boolean *enterEventMode, fmi2Boolean *terminateSimulation)
{
    (void)noSetFMUStatePriorToCurrentPoint;
    if (!c) return fmi2Error;
    if (enterEventMode) *enterEventMode = fmi2False;
    if (terminateSimulation) *terminateSimulation = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time)
{
    inst_t *m = (inst_t *)c;
    if (!m) return fmi2Error;
    m->t = time;
    return fmi2OK;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx)
{
    inst_t *m = (inst_t *)c;
    if (!m || nx != DCD_NX || !x) return fmi2Error;
    memcpy(m->x, x, sizeof m->x);
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real derivatives[], size_t nx)
{
    inst_t *m = (inst_t *)c;
    if (!m || nx != DCD_NX || !derivatives) return fmi2Error;
    dcd_rhs(m->p, m->t, m->x, m->on, derivatives, NULL);
    if (!all_finite(derivatives, DCD_NX)) {
        logmsg(m, fmi2Error, "logStatusError", "DCDrive: non-finite derivative at t=%g", m->t);
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t ni)
{ (void)z; return (c && ni == 0) ? fmi2OK : fmi2Error; }

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx)
{
    inst_t *m = (inst_t *)c;
    if (!m || nx != DCD_NX || !x) return fmi2Error;
    memcpy(x, m->x, sizeof m->x);
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x_nominal[], size_t nx)
{
    if (!c || nx != DCD_NX || !x_nominal) return fmi2Error;
    memcpy(x_nominal, dcd_x_nominal, sizeof dcd_x_nominal);
    return fmi2OK;
}

/* ---- Co-Simulation ---- */

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[])
{ (void)c; (void)vr; (void)order; (void)value; return nvr == 0 ? fmi2OK : fmi2Error; }

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[])
{ (void)c; (void)vr; (void)order; (void)value; return nvr == 0 ? fmi2OK : fmi2Error; }

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                      fmi2Real communicationStepSize, fmi2Boolean noSetFMUStatePriorToCurrentPoint)
{
    (void)noSetFMUStatePriorToCurrentPoint;
    inst_t *m = (inst_t *)c;
    if (!m || m->mode != M_STEP) return fmi2Error;
    if (!(communicationStepSize >= 0.0)) {
        logmsg(m, fmi2Error, "logStatusError", "DCDrive: negative step size %g",
               communicationStepSize);
        return fmi2Error;
    }
    if (fabs(currentCommunicationPoint - m->t) > 1e-9 * (1.0 + fabs(m->t))) {
        logmsg(m, fmi2Error, "logStatusError",
               "DCDrive: communication point %g does not match the FMU time %g",
               currentCommunicationPoint, m->t);
        return fmi2Error;
    }
    m->t = currentCommunicationPoint;
    const double tend = currentCommunicationPoint + communicationStepSize;
    double bp[2];
    const int nb = dcd_breakpoints(m->p, bp);
    long nsteps = 0;
    while (m->t < tend) {
        double tb = tend;
        for (int i = 0; i < nb; ++i)
            if (bp[i] > m->t && bp[i] < tb) { tb = bp[i]; break; }
        update_discrete(m);
        if (integrate_segment(m, tb, &nsteps) != fmi2OK) {
            m->mode = M_ERROR;
            return fmi2Error;
        }
    }
    m->t = tend;
    update_discrete(m);
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value)
{ (void)c; (void)s; (void)value; return fmi2Discard; }

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value)
{
    inst_t *m = (inst_t *)c;
    if (!m || !value) return fmi2Error;
    if (s == fmi2LastSuccessfulTime) { *value = m->t; return fmi2OK; }
    return fmi2Discard;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value)
{ (void)c; (void)s; (void)value; return fmi2Discard; }
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value)
{ (void)c; (void)s; (void)value; return fmi2Discard; }
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value)
{ (void)c; (void)s; (void)value; return fmi2Discard; }
