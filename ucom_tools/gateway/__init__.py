"""The CANopen CiA 402 gateway: a running UCoM robot's joints as CANopen drives
(``ucom gateway``)."""
