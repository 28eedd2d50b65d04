// Documentation only: the C sources in sources/ are the model (no Modelica compiler here).
// Same equations, constants, guards and parameter names as sources/model.c and docs/heattank.md.
model HeatTank "Electric water heater (10 L tank, immersion element) started cold by a supply step"
  // degradation inputs and candidate effects (FMU parameters)
  parameter Real element_R(unit="Ohm") = 26.45 "element.R: heating element resistance";
  parameter Real element_hA(unit="W/K") = 100 "element.hA: element-to-water conductance";
  parameter Real insulation_UA(unit="W/K") = 1.5 "insulation.UA: tank-to-ambient loss conductance";
  parameter Real sensor_tau(unit="s") = 0 "sensor.tau: temperature sensor lag";
  parameter Real sensor_offset(unit="K") = 0 "sensor.offset: temperature sensor offset";
  parameter Real supply_ratio = 1 "supply.ratio: supply voltage / 230 V";
  parameter Real inlet_flow(unit="kg/s") = 0 "inlet.flow: cold water drawn through the tank";
  parameter Real supply_delay(unit="s") = 0 "supply.delay: supply switched on late";
  // constants of the heater type
  constant Real Vnom = 230 "V", Ce = 4000 "J/K", Cw = 44000 "J/K", cp = 4186 "J/(kg.K)";
  constant Real Tamb = 20 "degC", Tin = 10 "degC", Tcut = 250 "degC";
  // states
  Real Te(start=Tamb, fixed=true) "state.Te (degC)";
  Real Tw(start=Tamb, fixed=true) "state.Tw (degC)";
  Real y(start=Tamb, fixed=true) "sensor.y (degC)";
  // algebraic
  Real v "supply.v (V)", q "element.q (W)", loss "loss.q (W)";
  // outputs
  output Real sensor_T "sensor.T (degC)", water_T "water.T (degC)", element_T "element.T (degC)";
  output Real heater_I "heater.I (A)", heater_P "heater.P (W)";
  discrete output Real cutout(start=0, fixed=true) "cutout (1)";
equation
  v = if time >= supply_delay then supply_ratio*Vnom else 0;
  heater_I = v/element_R;
  heater_P = v*heater_I;
  q = element_hA*(Te - Tw);
  loss = insulation_UA*(Tw - Tamb) + inlet_flow*cp*(Tw - Tin);
  Ce*der(Te) = heater_P - q;
  Cw*der(Tw) = q - loss;
  if sensor_tau > 0 then
    sensor_tau*der(y) = Tw - y;
  else
    der(y) = 0;
  end if;
  sensor_T = (if sensor_tau > 0 then y else Tw) + sensor_offset;
  water_T = Tw;
  element_T = Te;
  // thermal fuse of the element: latched once the sheath exceeds 250 degC
  when Te > Tcut then
    cutout = 1;
  end when;
end HeatTank;
