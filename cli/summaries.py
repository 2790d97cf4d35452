"""One line per subcommand: what ``gravcal --help`` lists, read without importing the commands (their imports
load numpy, python-can and the emulator rigs: ~1 s); each cli/cmd_<name>.py gives its parser the same line."""

SUMMARIES = {
    "demo": "simulated wearer -> ring buffer -> detector -> online estimator, converging live",
    "simulate": "write a simulated recording (CSV or .npy) and its true parameters (JSON)",
    "calibrate": "calibrate a recording or a whole study from its quasi-static moments",
    "reproduce": "re-run a paper's experiment (loetters: error vs θ, Sections 3-4)",
    "emulate": "emulate the logger on a serial pty, slcan pty, or fake I2C device",
    "watch": "print calibrated samples and calibration changes from gravcald",
    "daemon-demo": "run gravcald on the emulated logger and watch its calibration converge (one command)",
    "diagnose": "what the baseline simulation gets wrong on a recording, the cause, the held-out gain",
    "gyro": "in-use gyro calibration (bias, sensitivity) of a recording or measured dataset",
}
