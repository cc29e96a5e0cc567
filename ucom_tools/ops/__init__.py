"""Operations: what a user asks for (enumerate, flash, info ...), returning result
dataclasses.  No click, no rich, no printing."""
