"""The bundled virtual UCoM fleet: boards that speak the real protocol on simulated buses."""
