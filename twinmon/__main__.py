"""``python -m twinmon`` is the ``twinmon`` command."""
from .cli import main

main()
