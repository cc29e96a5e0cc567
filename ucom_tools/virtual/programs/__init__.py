"""Models of the DSP programs a virtual UCoM runs: the contract between a board's run time
and a model (:mod:`~ucom_tools.virtual.programs.base`), the models (ARMAR-III's
:mod:`~ucom_tools.virtual.programs.armar3` with its per-axis controller, LAURON-IV's
:mod:`~ucom_tools.virtual.programs.lauron4`, :mod:`~ucom_tools.virtual.programs.idle` for a
program without one), and :mod:`~ucom_tools.virtual.programs.catalogue`, which finds a
model by the program name of an image's descriptor."""
