// Documentation only: the C sources in sources/ are the model (no Modelica compiler here).
// Same equations, constants, guards and parameter names as sources/model.c and docs/dcdrive.md.
model DCDrive "Permanent-magnet DC motor started by a voltage step, driving a fan-like load"
  // degradation inputs and candidate effects (FMU parameters)
  parameter Real bearing_b(unit="N.m.s/rad") = 1e-3 "bearing.b: viscous bearing friction";
  parameter Real winding_R(unit="Ohm") = 1.0 "winding.R: armature circuit resistance";
  parameter Real tacho_tau(unit="s") = 0 "tacho.tau: tachometer lag";
  parameter Real tacho_gain = 1 "tacho.gain: tachometer scale";
  parameter Real supply_ratio = 1 "supply.ratio: supply voltage / 48 V";
  parameter Real load_extra(unit="N.m") = 0 "load.extra: extra load torque";
  parameter Real supply_delay(unit="s") = 0 "supply.delay: supply switched on late";
  parameter Real fan_c(unit="N.m.s2/rad2") = 7e-6 "fan.c: fan load coefficient";
  // constants of the drive type
  constant Real Vnom = 48 "V", Ke = 0.1 "V.s/rad", Kt = 0.1 "N.m/A", L = 5e-3 "H";
  constant Real J = 5e-3 "kg.m2", Tc = 1.0 "N.m", wc = 0.5 "rad/s";
  constant Real tCheck = 1.0 "s", wStall = 48 "rad/s";
  // states
  Real i(start=0, fixed=true) "state.i (A)";
  Real w(start=0, fixed=true) "state.w (rad/s)";
  Real y(start=0, fixed=true) "tacho.y (rad/s)";
  // algebraic
  Real v "supply.v (V)", emf "motor.emf (V)", load "load.torque (N.m)";
  // outputs
  output Real tacho_w "tacho.w (rad/s)", shaft_w "shaft.w (rad/s)";
  output Real armature_i "armature.i (A)", shaft_torque "shaft.torque (N.m)";
  discrete output Real stalled(start=0, fixed=true) "stalled (1)";
equation
  v = if time >= supply_delay then supply_ratio*Vnom else 0;
  emf = Ke*w;
  load = bearing_b*w + fan_c*w*abs(w) + (Tc + load_extra)*tanh(w/wc);
  L*der(i) = v - winding_R*i - emf;
  J*der(w) = Kt*i - load;
  if tacho_tau > 0 then
    tacho_tau*der(y) = w - y;
  else
    der(y) = 0;
  end if;
  tacho_w = tacho_gain*(if tacho_tau > 0 then y else w);
  shaft_w = w;
  armature_i = i;
  shaft_torque = Kt*i;
  // stall protection: one check, one second after switch-on
  when time >= max(supply_delay, 0) + tCheck then
    stalled = if w < wStall then 1 else 0;
  end when;
end DCDrive;
