"""One virtual UCoM: the board as a bus node (:mod:`~ucom_tools.virtual.board.ucom`), its
bootloader's services (:mod:`~ucom_tools.virtual.board.bootloader`: the init chain, Set
Status, Info and the reports), the programming transfer
(:mod:`~ucom_tools.virtual.board.programming`, :mod:`~ucom_tools.virtual.board.receiver`),
its non-volatile memory (:mod:`~ucom_tools.virtual.board.nvmem`), the DSP program it starts
(:mod:`~ucom_tools.virtual.board.application`) and that program's side of the run-time
exchange (:mod:`~ucom_tools.virtual.board.runtime`); what those parts may use of the board
(:mod:`~ucom_tools.virtual.board.port`); and mutant boards, with documented defects
(:mod:`~ucom_tools.virtual.board.mutants`)."""
