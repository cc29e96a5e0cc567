"""Host-side protocol clients: talk to UCoM boards over any python-can ``BusABC``."""
