"""``python -m virgi_ns.demo`` (what ``make demo`` runs)."""

from virgi_ns.demo.run import entrypoint

entrypoint()
