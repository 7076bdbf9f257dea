"""SINS + receiver clock stage of the ultra-tight engine: the strapdown mechanisation
(:func:`ultratight.ins.sins.sins_step`) corrected by the tight filter's error state (feedback),
and the receiver-clock bias/drift estimates propagated between updates."""

import numpy as np

from ultratight.constants import OMEGA_E
from ultratight.fusion.coupling import tight
from ultratight.ins.attitude import quat_to_dcm
from ultratight.ins import error_model, sins
from ultratight.ins.earth import dcm_ecef_from_enu, earth_rate_l, llh_to_ecef


class InsClock:
    """Corrected SINS plus receiver-clock estimates, from an initial attitude ``q_lb``, ENU velocity,
    position ``llh`` and clock bias (m) / drift (m/s)."""

    def __init__(self, q_lb, vel_l, llh, clk_bias_m, clk_drift_mps):
        self.x = sins.make_state(q_lb, vel_l, llh)
        self.clk_b = float(clk_bias_m)
        self.clk_d = float(clk_drift_mps)
        self.bg = np.zeros(3)        # estimated gyro bias (rad/s), removed from the increments
        self.ba = np.zeros(3)        # estimated accelerometer bias (m/s^2)
        self.f_b = np.zeros(3)       # last specific force (body), for the error model
        self.w_b = np.zeros(3)
        self.lever_b = None          # lever arm IMU -> antenna (FLU, m); None = antenna at the IMU

    def step(self, dtheta, dv, dt):
        dth = dtheta - self.bg * dt
        dvc = dv - self.ba * dt
        self.f_b = dvc / dt
        self.w_b = dth / dt
        sins.sins_step(self.x, dth, dvc, dt)
        self.clk_b += self.clk_d * dt

    def trial_velocity_e(self, dtheta, dv, dt):
        """ECEF velocity after one mechanisation step from the current state, without changing it."""
        x_try = self.x.copy()
        sins.sins_step(x_try, dtheta, dv, dt)
        return dcm_ecef_from_enu(x_try[7], x_try[8]) @ x_try[4:7]

    @property
    def llh(self):
        return self.x[7:10]

    @property
    def vel_l(self):
        return self.x[4:7]

    @property
    def q_lb(self):
        return self.x[0:4]

    def pos_vel_e(self):
        lat, lon, h = self.x[7], self.x[8], self.x[9]
        C_el = dcm_ecef_from_enu(lat, lon)
        return np.asarray(llh_to_ecef(lat, lon, h)), C_el @ self.x[4:7], C_el

    def antenna_pos_vel_e(self):
        """ECEF position and velocity of the antenna (and C_el): ``pos + C_eb l`` and
        ``vel + C_eb (omega_eb_b x l)`` with the last corrected gyro rate; the IMU's own
        :meth:`pos_vel_e` when there is no lever arm."""
        pos_e, vel_e, C_el = self.pos_vel_e()
        if self.lever_b is None:
            return pos_e, vel_e, C_el
        C_eb = C_el @ quat_to_dcm(self.x[0:4])
        w_eb = self.w_b - C_eb.T @ np.array([0.0, 0.0, OMEGA_E])
        return pos_e + C_eb @ self.lever_b, vel_e + C_eb @ np.cross(w_eb, self.lever_b), C_el

    def lever_terms(self):
        """(C_lb, l_l = C_lb l, a_l = C_lb (omega_ib_b x l), omega_ie_l) for the tight filter's
        measurement model (:func:`ultratight.fusion.coupling.tight.measurement_matrix`), or None without a
        lever arm."""
        if self.lever_b is None:
            return None
        C_lb = quat_to_dcm(self.x[0:4])
        return C_lb, C_lb @ self.lever_b, C_lb @ np.cross(self.w_b, self.lever_b), earth_rate_l(self.x[7])

    def feedback(self, dx):
        """Apply the tight filter's error state (estimate minus truth) and clear it."""
        error_model.apply_feedback(self.x, dx)      # attitude, velocity, position
        self.bg += dx[tight.BG]
        self.ba += dx[tight.BA]
        self.clk_b -= dx[tight.CLK_B]
        self.clk_d -= dx[tight.CLK_D]
