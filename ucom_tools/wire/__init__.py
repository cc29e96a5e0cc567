"""Wire format of the UCoM CAN protocol: pure encode/decode, no I/O.

The normative description is ``man/ucom-protocol.7``; every constant here is named there.
"""
