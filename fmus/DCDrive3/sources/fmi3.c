/*
 * DCDrive3 -- FMI 3.0 glue: Co-Simulation and Model Exchange in one binary.
 *
 * The model (model.c, model.h) and the co-simulation integrator (cs.c, cs.h) are the files
 * of fmus/DCDrive, linked here, so the physics exists once.  Differences from the FMI 2.0
 * build: Float64 variables, an independent variable `time`, and `stalled` is an Int32.
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"
#include "cs.h"

#define INSTANTIATION_TOKEN "{8d2f5a61-0e3b-4c7a-9f18-2a6b4c8d0e13}"

typedef enum {
    M_INSTANTIATED, M_INIT, M_EVENT, M_CONT, M_STEP, M_TERMINATED, M_ERROR
} mode_t_;

typedef struct {
    fmi3LogMessageCallback logger;
    fmi3InstanceEnvironment env;
    char name[256];
    int cs;            /* 1: Co-Simulation, 0: Model Exchange */
    int logging_on;
    int event_mode_used;
    mode_t_ mode;
    dcd_sim_t s;
} inst_t;

static void logmsg(inst_t *m, fmi3Status st, const char *cat, const char *fmt, ...)
{
    if (!m || !m->logger) return;
    if (st < fmi3Warning && !m->logging_on) return;
    char buf[512];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    m->logger(m->env, st, cat, buf);
}

static int all_finite(const double *x, int n)
{
    for (int i = 0; i < n; ++i) if (!isfinite(x[i])) return 0;
    return 1;
}

static int is_param(fmi3ValueReference v) { return v < DCD_NP; }

#define INST(c) inst_t *m = (inst_t *)(c); if (!m) return fmi3Error

/* ------------------------------------------------------------------------------------ */
/* inquire version, logging, instantiation                                                */

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[])
{
    (void)nCategories; (void)categories;
    INST(instance);
    m->logging_on = loggingOn ? 1 : 0;
    return fmi3OK;
}

static inst_t *new_instance(fmi3String instanceName, fmi3String token, int cs, fmi3Boolean loggingOn,
                            fmi3InstanceEnvironment env, fmi3LogMessageCallback logger)
{
    if (token && strcmp(token, INSTANTIATION_TOKEN) != 0) {
        if (logger) logger(env, fmi3Error, "logStatusError",
                           "DCDrive3: instantiation token does not match the model description");
        return NULL;
    }
    inst_t *m = (inst_t *)calloc(1, sizeof(inst_t));
    if (!m) return NULL;
    m->logger = logger;
    m->env = env;
    snprintf(m->name, sizeof m->name, "%s", instanceName ? instanceName : "DCDrive3");
    m->cs = cs;
    m->logging_on = loggingOn ? 1 : 0;
    dcd_sim_reset(&m->s);
    m->mode = M_INSTANTIATED;
    return m;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken,
                                          fmi3String resourcePath, fmi3Boolean visible,
                                          fmi3Boolean loggingOn,
                                          fmi3InstanceEnvironment instanceEnvironment,
                                          fmi3LogMessageCallback logMessage)
{
    (void)resourcePath; (void)visible;
    return new_instance(instanceName, instantiationToken, 0, loggingOn, instanceEnvironment,
                        logMessage);
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
                                         fmi3String resourcePath, fmi3Boolean visible,
                                         fmi3Boolean loggingOn, fmi3Boolean eventModeUsed,
                                         fmi3Boolean earlyReturnAllowed,
                                         const fmi3ValueReference requiredIntermediateVariables[],
                                         size_t nRequiredIntermediateVariables,
                                         fmi3InstanceEnvironment instanceEnvironment,
                                         fmi3LogMessageCallback logMessage,
                                         fmi3IntermediateUpdateCallback intermediateUpdate)
{
    (void)resourcePath; (void)visible; (void)earlyReturnAllowed;
    (void)requiredIntermediateVariables; (void)nRequiredIntermediateVariables;
    (void)intermediateUpdate;
    inst_t *m = new_instance(instanceName, instantiationToken, 1, loggingOn, instanceEnvironment,
                             logMessage);
    if (m) m->event_mode_used = eventModeUsed ? 1 : 0;
    return m;
}

fmi3Instance fmi3InstantiateScheduledExecution(fmi3String instanceName, fmi3String instantiationToken,
                                               fmi3String resourcePath, fmi3Boolean visible,
                                               fmi3Boolean loggingOn,
                                               fmi3InstanceEnvironment instanceEnvironment,
                                               fmi3LogMessageCallback logMessage,
                                               fmi3ClockUpdateCallback clockUpdate,
                                               fmi3LockPreemptionCallback lockPreemption,
                                               fmi3UnlockPreemptionCallback unlockPreemption)
{
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible;
    (void)loggingOn; (void)clockUpdate; (void)lockPreemption; (void)unlockPreemption;
    if (logMessage) logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                               "DCDrive3: Scheduled Execution is not supported");
    return NULL;
}

void fmi3FreeInstance(fmi3Instance instance) { free(instance); }

/* ------------------------------------------------------------------------------------ */
/* initialization, termination, reset                                                     */

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined,
                                       fmi3Float64 tolerance, fmi3Float64 startTime,
                                       fmi3Boolean stopTimeDefined, fmi3Float64 stopTime)
{
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    INST(instance);
    if (m->mode != M_INSTANTIATED) return fmi3Error;
    m->s.t = startTime;
    m->mode = M_INIT;
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance)
{
    INST(instance);
    if (m->mode != M_INIT) return fmi3Error;
    dcd_sim_update_discrete(&m->s);
    m->s.h = 0.0;
    m->mode = (m->cs && !m->event_mode_used) ? M_STEP : M_EVENT;
    return fmi3OK;
}

fmi3Status fmi3EnterEventMode(fmi3Instance instance)
{
    INST(instance);
    if (m->mode != M_CONT && m->mode != M_EVENT && m->mode != M_STEP) return fmi3Error;
    m->mode = M_EVENT;
    return fmi3OK;
}

fmi3Status fmi3Terminate(fmi3Instance instance)
{
    INST(instance);
    m->mode = M_TERMINATED;
    return fmi3OK;
}

fmi3Status fmi3Reset(fmi3Instance instance)
{
    INST(instance);
    dcd_sim_reset(&m->s);
    m->mode = M_INSTANTIATED;
    return fmi3OK;
}

/* ------------------------------------------------------------------------------------ */
/* getting and setting values                                                             */

fmi3Status fmi3GetFloat64(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                          fmi3Float64 values[], size_t nValues)
{
    INST(instance);
    if (nvr == 0) return fmi3OK;
    if (!vr || !values || nValues < nvr) return fmi3Error;
    double dx[DCD_NX];
    dcd_aux_t a;
    int have = 0;
    for (size_t k = 0; k < nvr; ++k) {
        const fmi3ValueReference v = vr[k];
        if (is_param(v)) { values[k] = m->s.p[v]; continue; }
        if (v >= VR_X0 && v < VR_X0 + DCD_NX) { values[k] = m->s.x[v - VR_X0]; continue; }
        switch (v) {
        case VR_TIME: values[k] = m->s.t; continue;
        case VR_TACHO_W: values[k] = dcd_tacho(m->s.p, m->s.x); continue;
        case VR_SHAFT_W: values[k] = m->s.x[X_W]; continue;
        case VR_ARMATURE_I: values[k] = m->s.x[X_I]; continue;
        default: break;
        }
        if (!have) { dcd_rhs(m->s.p, m->s.t, m->s.x, m->s.on, dx, &a); have = 1; }
        switch (v) {
        case VR_SHAFT_TORQUE: values[k] = a.torque; break;
        case VR_SUPPLY_V: values[k] = a.v; break;
        case VR_MOTOR_EMF: values[k] = a.emf; break;
        case VR_LOAD_TORQUE: values[k] = a.load; break;
        default:
            if (v >= VR_DX0 && v < VR_DX0 + DCD_NX) { values[k] = dx[v - VR_DX0]; break; }
            logmsg(m, fmi3Error, "logStatusError",
                   "DCDrive3: no Float64 variable with value reference %u", (unsigned)v);
            return fmi3Error;
        }
    }
    return fmi3OK;
}

fmi3Status fmi3SetFloat64(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                          const fmi3Float64 values[], size_t nValues)
{
    INST(instance);
    if (nvr == 0) return fmi3OK;
    if (!vr || !values || nValues < nvr) return fmi3Error;
    const int before_init = m->mode == M_INSTANTIATED || m->mode == M_INIT;
    for (size_t k = 0; k < nvr; ++k) {
        const fmi3ValueReference v = vr[k];
        if ((is_param(v) || (v >= VR_X0 && v < VR_X0 + DCD_NX)) && before_init) {
            if (!isfinite(values[k])) {
                logmsg(m, fmi3Error, "logStatusError",
                       "DCDrive3: non-finite value for value reference %u", (unsigned)v);
                return fmi3Error;
            }
            if (is_param(v)) m->s.p[v] = values[k]; else m->s.x[v - VR_X0] = values[k];
            continue;
        }
        logmsg(m, fmi3Error, "logStatusError",
               "DCDrive3: value reference %u cannot be set in the current state", (unsigned)v);
        return fmi3Error;
    }
    return fmi3OK;
}

fmi3Status fmi3GetInt32(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                        fmi3Int32 values[], size_t nValues)
{
    INST(instance);
    if (nvr == 0) return fmi3OK;
    if (!vr || !values || nValues < nvr) return fmi3Error;
    for (size_t k = 0; k < nvr; ++k) {
        if (vr[k] != VR_STALLED) {
            logmsg(m, fmi3Error, "logStatusError",
                   "DCDrive3: no Int32 variable with value reference %u", (unsigned)vr[k]);
            return fmi3Error;
        }
        values[k] = m->s.stalled;
    }
    return fmi3OK;
}

/* the model has no variables of the other types */
#define NO_GET(NAME, T) \
    fmi3Status NAME(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, \
                    T values[], size_t nValues) \
    { (void)instance; (void)vr; (void)values; (void)nValues; return nvr == 0 ? fmi3OK : fmi3Error; }
#define NO_SET(NAME, T) \
    fmi3Status NAME(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, \
                    const T values[], size_t nValues) \
    { (void)instance; (void)vr; (void)values; (void)nValues; return nvr == 0 ? fmi3OK : fmi3Error; }

NO_GET(fmi3GetFloat32, fmi3Float32)
NO_GET(fmi3GetInt8, fmi3Int8)
NO_GET(fmi3GetUInt8, fmi3UInt8)
NO_GET(fmi3GetInt16, fmi3Int16)
NO_GET(fmi3GetUInt16, fmi3UInt16)
NO_GET(fmi3GetUInt32, fmi3UInt32)
NO_GET(fmi3GetInt64, fmi3Int64)
NO_GET(fmi3GetUInt64, fmi3UInt64)
NO_GET(fmi3GetBoolean, fmi3Boolean)
NO_GET(fmi3GetString, fmi3String)
NO_SET(fmi3SetFloat32, fmi3Float32)
NO_SET(fmi3SetInt8, fmi3Int8)
NO_SET(fmi3SetUInt8, fmi3UInt8)
NO_SET(fmi3SetInt16, fmi3Int16)
NO_SET(fmi3SetUInt16, fmi3UInt16)
NO_SET(fmi3SetInt32, fmi3Int32)
NO_SET(fmi3SetUInt32, fmi3UInt32)
NO_SET(fmi3SetInt64, fmi3Int64)
NO_SET(fmi3SetUInt64, fmi3UInt64)
NO_SET(fmi3SetBoolean, fmi3Boolean)
NO_SET(fmi3SetString, fmi3String)

fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                         size_t valueSizes[], fmi3Binary values[], size_t nValues)
{ (void)instance; (void)vr; (void)valueSizes; (void)values; (void)nValues; return nvr == 0 ? fmi3OK : fmi3Error; }
fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                         const size_t valueSizes[], const fmi3Binary values[], size_t nValues)
{ (void)instance; (void)vr; (void)valueSizes; (void)values; (void)nValues; return nvr == 0 ? fmi3OK : fmi3Error; }
fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                        fmi3Clock values[])
{ (void)instance; (void)vr; (void)values; return nvr == 0 ? fmi3OK : fmi3Error; }
fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                        const fmi3Clock values[])
{ (void)instance; (void)vr; (void)values; return nvr == 0 ? fmi3OK : fmi3Error; }

/* ------------------------------------------------------------------------------------ */
/* not supported: dependencies, FMU state, derivatives, clocks, configuration mode         */

fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference,
                                               size_t *nDependencies)
{ (void)instance; (void)valueReference; (void)nDependencies; return fmi3Error; }
fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent,
                                       size_t elementIndicesOfDependent[],
                                       fmi3ValueReference independents[],
                                       size_t elementIndicesOfIndependents[],
                                       fmi3DependencyKind dependencyKinds[], size_t nDependencies)
{
    (void)instance; (void)dependent; (void)elementIndicesOfDependent; (void)independents;
    (void)elementIndicesOfIndependents; (void)dependencyKinds; (void)nDependencies;
    return fmi3Error;
}
fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState *FMUState)
{ (void)instance; (void)FMUState; return fmi3Error; }
fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState)
{ (void)instance; (void)FMUState; return fmi3Error; }
fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState *FMUState)
{ (void)instance; (void)FMUState; return fmi3Error; }
fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t *size)
{ (void)instance; (void)FMUState; (void)size; return fmi3Error; }
fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState,
                                 fmi3Byte serializedState[], size_t size)
{ (void)instance; (void)FMUState; (void)serializedState; (void)size; return fmi3Error; }
fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[],
                                   size_t size, fmi3FMUState *FMUState)
{ (void)instance; (void)serializedState; (void)size; (void)FMUState; return fmi3Error; }
fmi3Status fmi3GetDirectionalDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[],
                                        size_t nUnknowns, const fmi3ValueReference knowns[],
                                        size_t nKnowns, const fmi3Float64 seed[], size_t nSeed,
                                        fmi3Float64 sensitivity[], size_t nSensitivity)
{
    (void)instance; (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed;
    (void)nSeed; (void)sensitivity; (void)nSensitivity;
    return fmi3Error;
}
fmi3Status fmi3GetAdjointDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[],
                                    size_t nUnknowns, const fmi3ValueReference knowns[],
                                    size_t nKnowns, const fmi3Float64 seed[], size_t nSeed,
                                    fmi3Float64 sensitivity[], size_t nSensitivity)
{
    (void)instance; (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed;
    (void)nSeed; (void)sensitivity; (void)nSensitivity;
    return fmi3Error;
}
fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance) { (void)instance; return fmi3Error; }
fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance) { (void)instance; return fmi3Error; }
fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                  fmi3Float64 intervals[], fmi3IntervalQualifier qualifiers[])
{ (void)instance; (void)vr; (void)nvr; (void)intervals; (void)qualifiers; return fmi3Error; }
fmi3Status fmi3GetIntervalFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                   fmi3UInt64 counters[], fmi3UInt64 resolutions[],
                                   fmi3IntervalQualifier qualifiers[])
{ (void)instance; (void)vr; (void)nvr; (void)counters; (void)resolutions; (void)qualifiers; return fmi3Error; }
fmi3Status fmi3GetShiftDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                               fmi3Float64 shifts[])
{ (void)instance; (void)vr; (void)nvr; (void)shifts; return fmi3Error; }
fmi3Status fmi3GetShiftFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                fmi3UInt64 counters[], fmi3UInt64 resolutions[])
{ (void)instance; (void)vr; (void)nvr; (void)counters; (void)resolutions; return fmi3Error; }
fmi3Status fmi3SetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                  const fmi3Float64 intervals[])
{ (void)instance; (void)vr; (void)nvr; (void)intervals; return fmi3Error; }
fmi3Status fmi3SetIntervalFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                   const fmi3UInt64 counters[], const fmi3UInt64 resolutions[])
{ (void)instance; (void)vr; (void)nvr; (void)counters; (void)resolutions; return fmi3Error; }
fmi3Status fmi3SetShiftDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                               const fmi3Float64 shifts[])
{ (void)instance; (void)vr; (void)nvr; (void)shifts; return fmi3Error; }
fmi3Status fmi3SetShiftFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                const fmi3UInt64 counters[], const fmi3UInt64 resolutions[])
{ (void)instance; (void)vr; (void)nvr; (void)counters; (void)resolutions; return fmi3Error; }
fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference,
                                      fmi3Float64 activationTime)
{ (void)instance; (void)clockReference; (void)activationTime; return fmi3Error; }

/* ------------------------------------------------------------------------------------ */
/* event mode (Model Exchange, and Co-Simulation with event mode)                          */

fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance)
{
    INST(instance);
    return fmi3OK;
}

fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean *discreteStatesNeedUpdate,
                                    fmi3Boolean *terminateSimulation,
                                    fmi3Boolean *nominalsOfContinuousStatesChanged,
                                    fmi3Boolean *valuesOfContinuousStatesChanged,
                                    fmi3Boolean *nextEventTimeDefined, fmi3Float64 *nextEventTime)
{
    INST(instance);
    if (m->mode != M_EVENT) return fmi3Error;
    dcd_sim_update_discrete(&m->s);
    double bp[2];
    const int nb = dcd_breakpoints(m->s.p, bp);
    int defined = 0;
    double next = 0.0;
    for (int i = 0; i < nb; ++i)
        if (bp[i] > m->s.t) { defined = 1; next = bp[i]; break; }
    if (discreteStatesNeedUpdate) *discreteStatesNeedUpdate = fmi3False;
    if (terminateSimulation) *terminateSimulation = fmi3False;
    if (nominalsOfContinuousStatesChanged) *nominalsOfContinuousStatesChanged = fmi3False;
    if (valuesOfContinuousStatesChanged) *valuesOfContinuousStatesChanged = fmi3False;
    if (nextEventTimeDefined) *nextEventTimeDefined = defined ? fmi3True : fmi3False;
    if (nextEventTime) *nextEventTime = next;
    return fmi3OK;
}

/* ------------------------------------------------------------------------------------ */
/* Model Exchange                                                                         */

fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance)
{
    INST(instance);
    if (m->mode != M_EVENT) return fmi3Error;
    m->mode = M_CONT;
    return fmi3OK;
}

fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance,
                                       fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi3Boolean *enterEventMode, fmi3Boolean *terminateSimulation)
{
    (void)noSetFMUStatePriorToCurrentPoint;
    INST(instance);
    if (enterEventMode) *enterEventMode = fmi3False;
    if (terminateSimulation) *terminateSimulation = fmi3False;
    return fmi3OK;
}

fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time)
{
    INST(instance);
    m->s.t = time;
    return fmi3OK;
}

fmi3Status fmi3SetContinuousStates(fmi3Instance instance, const fmi3Float64 x[], size_t nx)
{
    INST(instance);
    if (nx != DCD_NX || !x) return fmi3Error;
    memcpy(m->s.x, x, sizeof m->s.x);
    return fmi3OK;
}

fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance instance, fmi3Float64 derivatives[],
                                             size_t nx)
{
    INST(instance);
    if (nx != DCD_NX || !derivatives) return fmi3Error;
    dcd_rhs(m->s.p, m->s.t, m->s.x, m->s.on, derivatives, NULL);
    if (!all_finite(derivatives, DCD_NX)) {
        logmsg(m, fmi3Error, "logStatusError", "DCDrive3: non-finite derivative at t=%g", m->s.t);
        return fmi3Error;
    }
    return fmi3OK;
}

fmi3Status fmi3GetEventIndicators(fmi3Instance instance, fmi3Float64 eventIndicators[], size_t ni)
{
    (void)eventIndicators;
    INST(instance);
    return ni == 0 ? fmi3OK : fmi3Error;
}

fmi3Status fmi3GetContinuousStates(fmi3Instance instance, fmi3Float64 x[], size_t nx)
{
    INST(instance);
    if (nx != DCD_NX || !x) return fmi3Error;
    memcpy(x, m->s.x, sizeof m->s.x);
    return fmi3OK;
}

fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance instance, fmi3Float64 nominals[], size_t nx)
{
    INST(instance);
    if (nx != DCD_NX || !nominals) return fmi3Error;
    memcpy(nominals, dcd_x_nominal, sizeof dcd_x_nominal);
    return fmi3OK;
}

fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t *nEventIndicators)
{
    INST(instance);
    if (!nEventIndicators) return fmi3Error;
    *nEventIndicators = 0;
    return fmi3OK;
}

fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t *nContinuousStates)
{
    INST(instance);
    if (!nContinuousStates) return fmi3Error;
    *nContinuousStates = DCD_NX;
    return fmi3OK;
}

/* ------------------------------------------------------------------------------------ */
/* Co-Simulation                                                                          */

fmi3Status fmi3EnterStepMode(fmi3Instance instance)
{
    INST(instance);
    if (!m->cs || (m->mode != M_EVENT && m->mode != M_STEP)) return fmi3Error;
    m->mode = M_STEP;
    return fmi3OK;
}

fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                    const fmi3Int32 orders[], fmi3Float64 values[], size_t nValues)
{
    (void)vr; (void)orders; (void)values; (void)nValues;
    INST(instance);
    return nvr == 0 ? fmi3OK : fmi3Error;
}

fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint,
                      fmi3Float64 communicationStepSize,
                      fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                      fmi3Boolean *eventHandlingNeeded, fmi3Boolean *terminateSimulation,
                      fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime)
{
    (void)noSetFMUStatePriorToCurrentPoint;
    INST(instance);
    if (eventHandlingNeeded) *eventHandlingNeeded = fmi3False;
    if (terminateSimulation) *terminateSimulation = fmi3False;
    if (earlyReturn) *earlyReturn = fmi3False;
    if (lastSuccessfulTime) *lastSuccessfulTime = m->s.t;
    if (m->mode != M_STEP) return fmi3Error;
    if (!(communicationStepSize >= 0.0)) {
        logmsg(m, fmi3Error, "logStatusError", "DCDrive3: negative step size %g",
               communicationStepSize);
        return fmi3Error;
    }
    if (fabs(currentCommunicationPoint - m->s.t) > 1e-9 * (1.0 + fabs(m->s.t))) {
        logmsg(m, fmi3Error, "logStatusError",
               "DCDrive3: communication point %g does not match the FMU time %g",
               currentCommunicationPoint, m->s.t);
        return fmi3Error;
    }
    m->s.t = currentCommunicationPoint;
    char msg[256];
    if (dcd_sim_advance(&m->s, currentCommunicationPoint + communicationStepSize,
                        msg, sizeof msg) != 0) {
        logmsg(m, fmi3Error, "logStatusError", "%s", msg);
        m->mode = M_ERROR;
        if (lastSuccessfulTime) *lastSuccessfulTime = m->s.t;
        return fmi3Error;
    }
    if (lastSuccessfulTime) *lastSuccessfulTime = m->s.t;
    return fmi3OK;
}
