"""The hardware a virtual board's DSP program drives: the FPGA behind the X: window
(:mod:`~ucom_tools.virtual.hardware.fpga`: registers, quadrature decoders) and the plants
behind it, the physical world of a plug-on board: one DC motor model
(:mod:`~ucom_tools.virtual.hardware.motor`), ARMAR-III's three-motor board
(:mod:`~ucom_tools.virtual.hardware.plant`) and the LAURON-IV leg
(:mod:`~ucom_tools.virtual.hardware.lauron4_leg`); and the numeric helpers the models
share (:mod:`~ucom_tools.virtual.hardware.numeric`)."""
