"""Method of characteristics (MOC): the time-domain model of the RPV rig (physics.md section 6).

It integrates the same physics as the frequency-domain model in :mod:`velab.model`
on a fixed characteristic grid (Covas et al. 2005), with what that model cannot
carry: the true quadratic steady friction, Brunone's unsteady friction and the valve's
orifice law (physics.md section 10). With the linearised friction and the imposed flow
it is an independent check of the frequency model (they share only the rig constants
and the imposed q(t)).

Entry points
------------
* :func:`moc_head` -- head at the valve on any sample grid, for the wall parameters
  of the calibration (a, J'_k, tau_k): the fast model for fitting and synthesis. The
  valve takes the rig's sigmoid as an imposed flow (the paper's model, what the fit's
  friction correction uses), or ``flow=`` another imposed flow, or ``opening=`` /
  ``position=`` the valve's opening or position through the orifice law;
* :func:`moc_transient` -- the same, with the flow through the valve (what the orifice
  law let through): synthetic runs and the simulated rig;
* :func:`moc_solve` -- the solver on its own grid, with the reservoir and valve flows,
  following the rig's valve law (``rig.valve.law``): for checks.

Formulation
-----------
Perturbation variables h = H - H_steady(x) and q = Q - Q0: the steady state is
exactly h = q = 0 (no start-up transient), and friction enters as the change of
the friction slope from its steady value, a dt (J(Q0 + q) - J(Q0)) per reach:

* ``"linear"``: R q, the tangent R = :attr:`velab.rig.Rig.linear_resistance`,
  exactly the friction of the frequency-domain model (the paper's);
* ``"quadratic"``: f ((Q0+q)|Q0+q| - Q0^2) / (2 g D A^2), Darcy-Weisbach with f
  frozen at the steady Reynolds number (in laminar flow Poiseuille's law, which is linear);
* ``"none"``.

Unsteady friction, at the foot of each characteristic too:

* ``"vardy-brown"``: the weighting-function convolution (Vardy-Brown turbulent,
  Zielke laminar; velab.friction) as a sum of exponentials, each a per-node history
  y_k <- exp(-n_k dtau) y_k + m_k (1 - exp(-n_k dtau))/(n_k dtau) dq, exact for q
  linear over a step (Trikha 1975; Vitkovsky et al. 2004); terms that die within one
  step are folded into one instantaneous weight (about 20 histories at 1 ms);
* ``"brunone"``: J_u = k3/(gA) (dq/dt + a sign(Q) |dq/dx|) (Brunone et al. 1991 with
  Vitkovsky's sign), dq/dt backwards at the foot, dq/dx over the reach the
  characteristic crosses. Nonlinear (sign, modulus): no frequency-domain form.

Viscoelastic wall: with F = alpha D rho g h / (2e) (hoop-stress change) and the
creep compliances J_k, every Kelvin-Voigt element obeys tau_k de_k/dt + e_k = J_k F.
The code carries e'_k = (2 a^2 / g) e_k, which has units of head and obeys
tau_k de'_k/dt + e'_k = J'_k h with the dimensionless J'_k = J_k a^2 rho alpha D/e of
:func:`velab.model.creep_scale` -- the same J'_k that build phi(s) in the frequency
model. The retarded-strain term of the characteristic equations is then
Sigma = dt * sum_k de'_k/dt at the new node P. The recursion that is exact for h
(hence F) linear over a step makes Sigma = G h_P + S_old, linear in h_P, so every
node is a 2 x 2 linear solve in closed form. Taking the creep rate at P makes the
scheme first order in dt (measured: the error halves with dt).

Characteristics (B = a / (g A)):

    C+:  h_P - h_A + B (q_P - q_A) + a dt J(q_A) + Sigma_P = 0
    C-:  h_P - h_B - B (q_P - q_B) - a dt J(q_B) + Sigma_P = 0

Friction is explicit (evaluated at the foot of the characteristic, A or B), as
in Covas et al. Boundaries: the reservoir node keeps h = 0 (so its wall never
creeps); the valve node takes the imposed q(t), or solves the orifice law of the
valve pair (velab.valvelaw) with C+: with h_P = c - b' q_P from C+ and X = Q0 + q_P,

    X^2 = K^2 (Hv0 + h_P),   K = Q0 tau / sqrt(Hv0),

a quadratic in X whose non-negative root is taken (X = 0 when the head would fall
below the free discharge: nothing flows back in through a valve discharging to air).
tau(t) is the valve pair's effective opening at each step, Hv0 = ``Rig.valve_head_m``.
The orifice law makes the transient nonlinear whatever the friction.

Grid: dx = a dt exactly, with N reaches. ``moc_solve`` takes N = round(L / (a dt))
and adjusts the *time step* to dt' = L / (N a) (``adjust="dt"``, default) so that
the wave speed, hence the Joukowsky head and the period, is exactly the requested
one, or keeps dt and uses a' = L / (N dt) (``adjust="wave_speed"``, Covas's
choice). ``moc_head`` takes N from the rig's nominal wave speed so that its output
is a smooth function of a (see :func:`velab.moc.head.n_reaches`).

The marching loop is compiled with numba (:mod:`velab.moc.kernel`): at the same 1 ms
step about 60x faster than the vectorised numpy loop it replaces; ``moc_head`` on
20 s at 1 kHz costs about 11 ms (docs/model.md, benchmarks/model_eval.py).
"""

from velab.moc.head import ValveTransient, commanded_opening, default_dt_s, moc_head, moc_transient, n_reaches, warm_up
from velab.moc.solver import FRICTION_LAWS, MocResult, grid, moc_solve, moc_valve_head

__all__ = ["FRICTION_LAWS", "MocResult", "ValveTransient", "commanded_opening", "default_dt_s", "grid", "moc_head",
           "moc_solve", "moc_transient", "moc_valve_head", "n_reaches", "warm_up"]
