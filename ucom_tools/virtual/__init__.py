"""The bundled virtual UCoM fleet: boards that speak the real protocol on simulated buses.

Its subsystems are packages, lowest first; each imports only those above it in this list:

- :mod:`~ucom_tools.virtual.bus`: the simulated CAN bus (arbitration, bit timing, load,
  the init line), the fleet clock every bus and board runs on, and frames lost on purpose;
- :mod:`~ucom_tools.virtual.hardware`: what a board's DSP program drives: the FPGA and,
  behind it, the plants (motors, gears, joints and sensors of a plug-on board);
- :mod:`~ucom_tools.virtual.programs`: models of the DSP programs (the control they run)
  and their contract with the board;
- :mod:`~ucom_tools.virtual.board`: one virtual UCoM: its bootloader, init chain,
  programming transfer, non-volatile memory, the program it starts and that program's
  run-time exchange; mutant boards;
- the modules of this package put them together: :mod:`~ucom_tools.virtual.fleet` (every
  bus and board of a topology), :mod:`~ucom_tools.virtual.injected` (injected faults
  applied to a fleet), :mod:`~ucom_tools.virtual.canbus` (a fleet as a python-can
  interface);
- :mod:`~ucom_tools.virtual.serve`: ``ucom fleet serve``, a fleet served to other
  processes with the socketcand protocol.

The PC's operations (``ucom_tools.ops``) never import it: they reach the fleet through
python-can like real hardware.
"""
