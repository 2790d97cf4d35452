"""gravcal.drivers: buses and framing only (serial, I2C, CAN), their fakes and the emulator."""
