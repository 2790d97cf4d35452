"""gravcal.daemon: wiring and service: gravcald, socket protocol, persistence, systemd, CLI."""
