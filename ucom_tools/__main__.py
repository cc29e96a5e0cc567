"""``python -m ucom_tools`` runs the ``ucom`` command."""

from ucom_tools.cli.main import main

main()
