"""Array layout of the scalar tracking bank (:mod:`ultratight.receiver.dsp.tracking`): channel modes,
the columns of the loop state, of the kernel's parameter vector and of the epoch records, and the
record flags.

The compiled block kernel (:mod:`ultratight.receiver.dsp.tracking_block`) reads and writes these
arrays by the indices below; the receiver stages (observables, navigation bits, outputs) read the
records ``rec_f`` (columns ``R_*``, names :data:`REC_F_NAMES`) and ``rec_i`` (columns ``RI_*``,
names :data:`REC_I_NAMES`, flags ``FL_*``) one row per code-period epoch.
"""

# channel modes
MODE_OFF, MODE_PULL, MODE_TRACK, MODE_LOST = 0, 1, 2, 3

# float state columns (sf)
(F_DOPP, F_PLL_X, F_PLL_Y, F_DLL_Z, F_PREV_I, F_PREV_Q, F_AIP, F_AQP, F_AIE, F_AQE, F_AIL, F_AQL,
 F_AT, F_CN0_P, F_CN0_T, F_CN0_DB, F_PLI_N, F_PLI_D, F_PLI, F_BIT_SUM, F_LOCK_T, F_UNLOCK_T,
 F_LOW_T, F_CARR_ACC, F_LAST_I, F_DLL_ERR, F_PLL_ERR, F_FLL_ERR, F_DLL_U) = range(29)
N_SF = 29
# int state columns (si)
(S_MODE, S_EPOCH, S_BIT_PHASE, S_NTRANS, S_HAVE_PREV, S_ACC_N, S_CN0_N, S_BIT_N, S_CN0_VALID,
 S_ACC_COH) = range(10)
N_SI = 10

# parameter vector (prm)
(P_PULL_PLL_BW, P_PULL_FLL_BW, P_PULL_DLL_BW, P_TRK_PLL_BW, P_TRK_FLL_BW, P_TRK_DLL_BW, P_PLL_ORDER,
 P_DLL_ORDER, P_COH_MS, P_SPACING, P_CN0_WIN, P_CN0_LOST, P_LOST_S, P_PLI_LOCK, P_LOCK_S, P_UNLOCK_S,
 P_BS_MARGIN, P_PLI_TAU, P_MAX_BNT, P_CN0_ALPHA, P_WEAK_DBHZ, P_PULL_COH_MS, P_WEAK_LONG_COH_MS,
 P_WEAK_PLL_BW, P_PEL, P_BS_ENERGY, P_CODE_LEN, P_CHIP_RATE, P_CARRIER) = range(29)
N_PRM = 29          # the last three: the signal's code length (chips), chip rate and carrier (Hz)

# record columns: float (rf) and int (ri)
(R_CODE_PHASE, R_CODE_RATE, R_CARR_ACC, R_DOPP, R_IP, R_QP, R_IE, R_QE, R_IL, R_QL, R_CN0, R_PLI,
 R_DLL_ERR, R_PLL_ERR, R_FLL_ERR, R_BIT) = range(16)
N_RF = 16
REC_F_NAMES = ("code_phase_chips", "code_rate_cps", "carr_acc_cycles", "doppler_hz", "I_P", "Q_P", "I_E",
               "Q_E", "I_L", "Q_L", "cn0_dbhz", "pli", "dll_err_chips", "pll_err_cycles", "fll_err_hz",
               "bit_soft")
(RI_PTR, RI_N, RI_EPOCH, RI_MODE, RI_FLAGS) = range(5)
N_RI = 5
REC_I_NAMES = ("sample_index", "n_samples", "epoch", "mode", "flags")
# flags
FL_BIT_DONE, FL_BIT_SYNC, FL_PLL_LOCK, FL_LOOP_UPD = 1, 2, 4, 8

STATE_NAMES = ("doppler_hz", "pll_x_hz", "pll_y_hz_s", "dll_z_cps", "prev_I", "prev_Q", "acc_I_P", "acc_Q_P",
               "acc_I_E", "acc_Q_E", "acc_I_L", "acc_Q_L", "acc_t_s", "cn0_power_sum", "cn0_time_s", "cn0_dbhz",
               "pli_num", "pli_den", "pli", "bit_sum", "lock_t_s", "unlock_t_s", "low_cn0_t_s",
               "carrier_acc_cycles", "last_I_P", "dll_err_chips", "pll_err_cycles", "fll_err_hz", "dll_u_cps")
"""Names of the float loop-state columns ``TrackingState.sf`` (indices ``F_*``; the first four are
the loop filters' states)."""
assert len(STATE_NAMES) == N_SF
P_DOPP, P_PLL_X, P_PLL_Y, P_DLL_Z = F_DOPP, F_PLL_X, F_PLL_Y, F_DLL_Z   # state indices of the loop filters
