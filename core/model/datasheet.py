"""Datasheet values and spreads of the board's sensors (ADXL210E pair, ENC-03J), with their sources.

Every constant names its source; ``docs/sensor-model.md`` lists them with the status of each
("verified" against a datasheet text, "as recalled" = not verified, or "assumed" = design choice).
Spreads: where the datasheet gives min/max, a part is drawn from a normal with the typical value as
mean and (max - min)/6 as standard deviation (min/max ~ +-3 sigma), clipped to min/max. Effects
given as "+-typ" with no sign are drawn zero-mean with sigma = typ.
"""
from __future__ import annotations

# --- ADXL210E (Analog Devices datasheet, rev. 0) -----------------------------------------
SENS_TYP = 0.04  # duty/g; verified: A(g) = (T1/T2 - 0.5)/4 %
SENS_LIMITS = (0.032, 0.048)  # duty/g min/max; as recalled (+-20 %)
D0_TYP = 0.50  # zero-g duty cycle; verified: "0 g = 50 % duty cycle"
D0_LIMITS = (0.42, 0.58)  # as recalled (+-2 g of offset at 4 %/g)
NOISE_DENSITY_UG = 200.0  # µg/√Hz; verified for ADXL210E (ADXL202/210 rev. B: 500)
RANGE_G = 10.0  # verified: full scale +-10 g
RSET_OHM = 625e3  # assumed: T2 = RSET/125 Mohm (verified formula) = 5 ms, inside 0.5-10 ms (verified)
RSET_TOL = 0.01  # assumed: 1 % resistor
CX_UF = 0.47  # assumed filter capacitor: f_3dB = 5 µF / C = 10.6 Hz (5 µF/C as recalled; = 1/(2 pi 32 kohm C))
CX_TOL = 0.10  # assumed: 10 % ceramic capacitor
ALIGN_DEG = 1.0  # +-1° in-die alignment error; as recalled (cross-axis sensitivity +-2 %)
CHIP_PLACEMENT_DEG = 0.5  # assumed: package placement on the PCB
MOUNT_B_DEG = 2.0  # assumed: chip B's hand-soldered edge carrier
TEMP_OFFSET_G_PER_C = 2e-3  # +-2 mg/°C zero-g drift; as recalled
TEMP_SENS_PER_C = 1e-4  # +-0.01 %/°C (+-0.5 % over 25..75 °C); as recalled
NONLIN_PCT_FS = 0.2  # +-0.2 % of full scale; as recalled
# assumed (no ADXL210 figure): the die trails the board's temperature sensor through the package and the
# PCB; plastic/ceramic packages on a small board in a housing give time constants of tens of seconds to
# tens of minutes (package junction-to-board figures of tens of s, board plus housing minutes)
THERMAL_LAG_TAU_S = 300.0
THERMAL_LAG_TAU_GRID_S = (30.0, 3600.0)  # assumed range over which the lag is profiled, log-spaced
T2_TEMPCO_PPM = 100.0  # assumed oscillator tempco; cancels in T1/T2
# --- supply and drift (the supply offset as recalled, the rest assumed) ---------------------
V_NOMINAL = 3.3  # V, reference supply of the board
SUPPLY_GAIN_PER_V = 5e-3  # assumed: 0.5 %/V sensitivity change
SUPPLY_OFFSET_G_PER_V = 0.25  # as recalled: 0 g duty cycle vs supply 1.0 %/V (ADXL202E/210E) = 250 mg/V at 4 %/g
OFFSET_RATE_G_PER_H = 1e-3  # assumed: 1 mg/h (Lötters 1998: offsets drift much more than sensitivities)
OFFSET_WALK_G_PER_SQRT_H = 2e-3  # assumed
SENS_RATE_PER_H = 2e-4  # assumed: 0.02 %/h
SENS_WALK_PER_SQRT_H = 5e-4  # assumed
BIAS_INSTABILITY_G = 0.5e-3  # assumed: colored-noise std
BIAS_TAU_S = (1.0, 10.0, 100.0)  # assumed: Gauss-Markov times spanning the 1/f region
TIMER_CLOCK_HZ = 4e6  # assumed microcontroller capture clock
# --- Murata ENC-03J ------------------------------------------------------------------------
GYRO_SCALE_MV_PER_DPS = 0.67  # as recalled; spread +-20 % as recalled
GYRO_SCALE_TOL = 0.20
GYRO_NULL_V = 1.35  # as recalled; spread assumed +-0.15 V
GYRO_NULL_TOL_V = 0.15
GYRO_RANGE_DPS = 300.0  # as recalled
GYRO_NOISE_DPS_RTHZ = 0.05  # assumed
GYRO_NULL_TEMPCO_MV_PER_C = 0.5  # assumed (removed by the high-pass anyway)
GYRO_HP_HZ = 0.3  # assumed conditioning stage (Scapellato 2005 gives no values)
GYRO_GAIN = 7.5  # assumed: +-300 °/s * 0.67 mV * 7.5 = +-1.5 V around Vsupply/2
GYRO_LP_HZ = 25.0  # assumed; below the sensor's own response (as recalled: 50 Hz)
GYRO_ADC_BITS = 12
