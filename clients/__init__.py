"""gravcal.clients: programs that read gravcald's socket (docs/socket-protocol.md)."""
