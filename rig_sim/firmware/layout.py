"""Memory layout shared by the compiled kernel and the Python side of the board.

Plain integer constants so that numba folds them at compile time.
"""

# --- settings written by the host (float64 vector `cfg`) ---------------------
CFG_KP = 0            # proportional gain (N/m or (m/s^2)/m)
CFG_KD = 1            # derivative gain (N s/m or (m/s^2) s/m)
CFG_PHASE_MODE = 2    # 0: target phase = forcing phase; 1: locked to the response
CFG_FREQ = 3          # forcing / phase-lock frequency, Hz
CFG_PARAM = 4         # airspeed (m/s) or forcing amplitude (m/s^2)
CFG_CLAMP = 5         # output clamp, |u| <= clamp (N or m/s^2)
CFG_TRIP = 6          # amplitude trip level on |x| (m)
CFG_NAVG = 7          # periods in the running mean/variance
CFG_FILTER_HZ = 8     # low-pass cutoff of the error filter (0: off)
CFG_TARGET = 9        # 15 target coefficients: a0, a1..a7 (cos), b1..b7 (sin)
NCOEF = 15
NHARM = 7
CFG_RING_DEC = CFG_TARGET + NCOEF   # ring buffer keeps every Nth sample
CFG_SIZE = CFG_RING_DEC + 1

# --- rig constants (float64 vector `rig`), fixed at start-up -----------------
RIG_KIND = 0          # 0 flutter, 1 oscillator
RIG_DT = 1
RIG_SAT = 2           # actuator saturation (N or m/s^2)
RIG_SIGMA = 3         # process-noise intensity
RIG_NOISE = 4         # 4 sensor-noise standard deviations: x, x', q2, q2'
RIG_LSB = 8           # 4 ADC quantisation steps
RIG_FS = 12           # 4 ADC full scales
RIG_MASS = 16         # oscillator modal mass (kg), for plugin/effect forces
RIG_LATENCY = 17      # actuator latency, samples
RIG_U_FS = 18         # full scale of the control/target/param channels in the ring buffer
RIG_PARAM_FS = 19
RIG_SIZE = 20

# --- continuous firmware state (float64 vector `fw`) -------------------------
FW_TH_FORCE = 0       # forcing phase in [0, 2pi)
FW_TH_PREV = 1        # previous estimator phase, wrapped
FW_TH_UNWRAP = 2      # estimator phase unwrapped within the current period
FW_EF = 3             # filtered error
FW_EDF = 4            # filtered error rate
FW_U = 5              # last control output (after clamp)
FW_XM = 6             # last measured x, x', q2, q2'
FW_TGT = 10           # last target and its rate
FW_TGTD = 11
FW_EXC = 12           # last total excitation
FW_PERIOD_T = 13      # time spent in the current period
FW_TH_EST = 14        # last estimator phase (wrapped)
FW_SIZE = 16

# --- integer firmware state (int64 vector `ic`) ------------------------------
IC_SEQ = 0            # samples since start
IC_PERIODS = 1        # completed estimator periods
IC_SAT = 2            # samples with the output saturated/clamped
IC_FAULT = 3          # latched fault code (0 none)
IC_ARMED = 4          # output enabled
IC_HIST_N = 5         # periods held in the history
IC_HIST_POS = 6
IC_DELAY_POS = 7
IC_TRIPS = 8
IC_RING_HEAD = 9      # records written to the ring
IC_SIZE = 10

# fault codes
FAULT_NONE = 0
FAULT_TRIP = 1        # amplitude trip
FAULT_WATCHDOG = 2    # host heartbeat lost
FAULT_DIVERGED = 3    # the state left the physical range (numerical or real blow-up)

# --- Fourier channels ---------------------------------------------------------
CH_RESPONSE = 0       # controlled coordinate (heave / displacement)
CH_CONTROL = 1        # control output after clamp
CH_EXCITATION = 2     # total excitation (forcing + control for the oscillator)
CH_SECOND = 3         # second coordinate (pitch for the aerofoil; 0 for the oscillator)
NCH = 4
HIST_MAX = 32         # most periods averaged
DELAY_MAX = 64        # longest actuator latency, samples

# --- ring buffer of samples (uint16 records) ---------------------------------
REC_SEQ = 0           # low 16 bits of the sample counter
REC_X = 1
REC_XD = 2
REC_Q2 = 3
REC_Q2D = 4
REC_TARGET = 5
REC_CONTROL = 6
REC_PARAM = 7
REC_PHASE = 8
REC_SIZE = 9
RING_CAP = 4096
