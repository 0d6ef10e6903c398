"""Sub-commands of the ``jtraj`` CLI; see :mod:`jtraj.cli` for the protocol."""
