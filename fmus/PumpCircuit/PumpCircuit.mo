// Documentation only: the C sources in sources/ are the model (no Modelica compiler here).
// Same equations, constants, guards and parameter names as sources/model.c and docs/model.md.
model PumpCircuit "Motor -> centrifugal pump -> pipe -> control valve -> open tank (after ThermoSysPro)"
  import Modelica.Constants.pi;
  // degradation inputs and candidate effects (FMU parameters)
  parameter Real motor_D(unit="N.m.s/rad") = 10 "motor.D: motor damping";
  parameter Real pump_b2(unit="s/m3") = 3.61 "pump.b2: efficiency coefficient";
  parameter Real sensor_tau(unit="s") = 0 "sensor.tau: flowmeter lag";
  parameter Real sensor_gain = 1 "sensor.gain: flowmeter scale";
  parameter Real valve_opening_time(unit="s") = 0 "valve.opening_time";
  parameter Real pipe_fouling = 0 "pipe.fouling";
  parameter Real pump_leak = 0 "pump.leak (m3/(s.Pa^0.5))";
  parameter Real motor_start_delay(unit="s") = 0 "motor.start_delay";
  parameter Real motor_supply_ratio = 1 "motor.supply_ratio";
  parameter Real valve_opening = 0.16425 "valve.opening (tuned: 400 kg/s nominal)";
  // constants
  constant Real Ualim = 380, Vrot = 1400, Lm = 1, Rm = 1e-5, Ki = 1, Jm = 4, Jp = 10;
  constant Real a1 = -88.67, a2 = 0, a3 = 43.15, b1 = -3.7751, b3 = -0.0075464, rhmin = 0.05;
  constant Real Cf0 = 10, rho = 998, g = 9.80665, L = 10, Dp = 0.2, lambda = 0.03;
  constant Real Kv = 1.733e12, Cvmax = 8005.42, weps = 1e-3;
  final constant Real wn = Vrot*pi/30, Km = 30*Ualim/(pi*Vrot), A = pi*Dp^2/4;
  // states
  Real w(start=0, fixed=true) "motor.omega (rad/s)";
  Real I(start=0, fixed=true) "motor.Im (A)";
  Real Q(start=0, fixed=true) "pipe.Q (kg/s)";
  Real y(start=0, fixed=true) "sensor.y (kg/s)";
  // algebraic
  Real R, qi, hn, dp, rh_raw, rh, Ch, Cf, Um, opening_eff, Cv, dP_pipe, dP_valve;
  // outputs
  output Real sensor_m_flow, pump_m_flow, motor_w, pump_dp, motor_I;
  output Real nonphysical(start=0, fixed=true) "latched";
equation
  R = w/wn;
  qi = Q/rho + pump_leak*sqrt(max(dp, 0));          // implicit; solved by Newton in C
  hn = a1*qi*abs(qi) + a2*qi*R + a3*R*abs(R);
  dp = rho*g*hn;
  rh_raw = if abs(R) < 1e-6 then b3 else b1*(qi/R)^2 + pump_b2*(qi/R) + b3;
  rh = max(rh_raw, rhmin);
  Ch = rho*g*qi*hn*w/(rh*(w^2 + weps^2));           // regularised rho*g*qi*hn/(rh*w)
  Cf = if abs(R) < 1 then Cf0*(1 - abs(R)) else 0;
  Um = if time >= motor_start_delay then motor_supply_ratio*Ualim else 0;
  (Jm + Jp)*der(w) = Ki*I - motor_D*w - Ch - Cf;
  Lm*der(I) = Um - Km*w - Rm*I;
  opening_eff = if valve_opening_time > 0 then valve_opening*max(min(time/valve_opening_time, 1), 0.01)
                else valve_opening;
  Cv = opening_eff*Cvmax;
  dP_pipe = (1 + pipe_fouling)*lambda*L/Dp*Q*abs(Q)/(2*A^2*rho);
  dP_valve = (1 + pipe_fouling)*Kv*Q*abs(Q)/(rho^2*Cv^2);
  (L/A)*der(Q) = dp - dP_pipe - dP_valve;
  der(y) = if sensor_tau > 0 then (Q - y)/sensor_tau else 0;
  sensor_m_flow = sensor_gain*(if sensor_tau > 0 then y else Q);
  pump_m_flow = Q;
  motor_w = w;
  pump_dp = dp;
  motor_I = I;
  when R > 0.1 and rh_raw <= rhmin and qi/R > pump_b2/(2*abs(b1)) then
    nonphysical = 1;
  end when;
end PumpCircuit;
