/*
 * HeatTank -- FMI 2.0 glue: Model Exchange and Co-Simulation in one binary.
 *
 * Co-Simulation integrates the equations of model.c with the adaptive Dormand-Prince 5(4)
 * scheme of cs.c (rtol 1e-10), which lands exactly on communication points and on the
 * model's breakpoint (supply switched on at supply.delay).  Model Exchange announces the
 * same breakpoint as a time event and checks the element's thermal fuse after every
 * completed integrator step.
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "cs.h"

typedef enum { M_INSTANTIATED, M_INIT, M_EVENT, M_CONT, M_STEP, M_TERMINATED, M_ERROR } mode_t_;

typedef struct {
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    char name[256];
    fmi2Type type;
    int logging_on;
    mode_t_ mode;
    ht_sim_t s;       /* parameters, states, time, discrete state */
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

static int all_finite(const double *x, int n)
{
    for (int i = 0; i < n; ++i) if (!isfinite(x[i])) return 0;
    return 1;
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
    snprintf(m->name, sizeof m->name, "%s", instanceName ? instanceName : "HeatTank");
    m->type = fmuType;
    m->logging_on = loggingOn ? 1 : 0;
    ht_sim_reset(&m->s);
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
    m->s.t = startTime;
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
    ht_sim_update_discrete(&m->s);
    m->s.h = 0.0;
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
    ht_sim_reset(&m->s);
    m->mode = M_INSTANTIATED;
    return fmi2OK;
}

static int is_param(fmi2ValueReference v) { return v < HT_NP; }

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[])
{
    inst_t *m = (inst_t *)c;
    if (!m) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    if (!vr || !value) return fmi2Error;
    double dx[HT_NX];
    ht_aux_t a;
    int have = 0;
    for (size_t k = 0; k < nvr; ++k) {
        const fmi2ValueReference v = vr[k];
        if (is_param(v)) { value[k] = m->s.p[v]; continue; }
        if (v >= VR_X0 && v < VR_X0 + HT_NX) { value[k] = m->s.x[v - VR_X0]; continue; }
        switch (v) {
        case VR_SENSOR_T: value[k] = ht_sensor(m->s.p, m->s.x); continue;
        case VR_WATER_T: value[k] = m->s.x[X_TW]; continue;
        case VR_ELEMENT_T: value[k] = m->s.x[X_TE]; continue;
        case VR_CUTOUT: value[k] = (double)m->s.cutout; continue;
        default: break;
        }
        if (!have) { ht_rhs(m->s.p, m->s.t, m->s.x, m->s.on, dx, &a); have = 1; }
        switch (v) {
        case VR_HEATER_I: value[k] = a.i; break;
        case VR_HEATER_P: value[k] = a.p; break;
        case VR_SUPPLY_V: value[k] = a.v; break;
        case VR_ELEMENT_Q: value[k] = a.q; break;
        case VR_LOSS_Q: value[k] = a.loss; break;
        default:
            if (v >= VR_DX0 && v < VR_DX0 + HT_NX) { value[k] = dx[v - VR_DX0]; break; }
            logmsg(m, fmi2Error, "logStatusError", "HeatTank: unknown value reference %u",
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
        if ((is_param(v) || (v >= VR_X0 && v < VR_X0 + HT_NX)) && before_init) {
            if (!isfinite(value[k])) {
                logmsg(m, fmi2Error, "logStatusError",
                       "HeatTank: non-finite value for value reference %u", (unsigned)v);
                return fmi2Error;
            }
            if (is_param(v)) m->s.p[v] = value[k]; else m->s.x[v - VR_X0] = value[k];
            continue;
        }
        logmsg(m, fmi2Error, "logStatusError",
               "HeatTank: value reference %u cannot be set in the current state", (unsigned)v);
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
    ht_sim_update_discrete(&m->s);
    double bp[1];
    const int nb = ht_breakpoints(m->s.p, bp);
    ei->newDiscreteStatesNeeded = fmi2False;
    ei->terminateSimulation = fmi2False;
    ei->nominalsOfContinuousStatesChanged = fmi2False;
    ei->valuesOfContinuousStatesChanged = fmi2False;
    ei->nextEventTimeDefined = fmi2False;
    ei->nextEventTime = 0.0;
    for (int i = 0; i < nb; ++i) {
        if (bp[i] > m->s.t) {
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
    inst_t *m = (inst_t *)c;
    if (!m) return fmi2Error;
    if (ht_over_temperature(m->s.x)) m->s.cutout = 1;
    if (enterEventMode) *enterEventMode = fmi2False;
    if (terminateSimulation) *terminateSimulation = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time)
{
    inst_t *m = (inst_t *)c;
    if (!m) return fmi2Error;
    m->s.t = time;
    return fmi2OK;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx)
{
    inst_t *m = (inst_t *)c;
    if (!m || nx != HT_NX || !x) return fmi2Error;
    memcpy(m->s.x, x, sizeof m->s.x);
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real derivatives[], size_t nx)
{
    inst_t *m = (inst_t *)c;
    if (!m || nx != HT_NX || !derivatives) return fmi2Error;
    ht_rhs(m->s.p, m->s.t, m->s.x, m->s.on, derivatives, NULL);
    if (!all_finite(derivatives, HT_NX)) {
        logmsg(m, fmi2Error, "logStatusError", "HeatTank: non-finite derivative at t=%g", m->s.t);
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t ni)
{ (void)z; return (c && ni == 0) ? fmi2OK : fmi2Error; }

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx)
{
    inst_t *m = (inst_t *)c;
    if (!m || nx != HT_NX || !x) return fmi2Error;
    memcpy(x, m->s.x, sizeof m->s.x);
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x_nominal[], size_t nx)
{
    if (!c || nx != HT_NX || !x_nominal) return fmi2Error;
    memcpy(x_nominal, ht_x_nominal, sizeof ht_x_nominal);
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
        logmsg(m, fmi2Error, "logStatusError", "HeatTank: negative step size %g",
               communicationStepSize);
        return fmi2Error;
    }
    if (fabs(currentCommunicationPoint - m->s.t) > 1e-9 * (1.0 + fabs(m->s.t))) {
        logmsg(m, fmi2Error, "logStatusError",
               "HeatTank: communication point %g does not match the FMU time %g",
               currentCommunicationPoint, m->s.t);
        return fmi2Error;
    }
    m->s.t = currentCommunicationPoint;
    char msg[256];
    if (ht_sim_advance(&m->s, currentCommunicationPoint + communicationStepSize,
                        msg, sizeof msg) != 0) {
        logmsg(m, fmi2Error, "logStatusError", "%s", msg);
        m->mode = M_ERROR;
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value)
{ (void)c; (void)s; (void)value; return fmi2Discard; }

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value)
{
    inst_t *m = (inst_t *)c;
    if (!m || !value) return fmi2Error;
    if (s == fmi2LastSuccessfulTime) { *value = m->s.t; return fmi2OK; }
    return fmi2Discard;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value)
{ (void)c; (void)s; (void)value; return fmi2Discard; }
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value)
{ (void)c; (void)s; (void)value; return fmi2Discard; }
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value)
{ (void)c; (void)s; (void)value; return fmi2Discard; }
