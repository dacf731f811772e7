"""CNC-side parts of fbgcomp that run outside fbgcomp's own environment.

``fbgcomp_hal`` is the LinuxCNC userspace HAL component; it runs under the *system* Python 3
(Debian's ``linuxcnc-uspace`` ships the ``hal`` module for ``/usr/bin/python3`` only), so it uses
the standard library alone and imports ``hal`` only when started as a component. Its packet
format and limiter are imported from here by :mod:`fbgcomp.runtime.outputs.linuxcnc`, so both sides of
the local channel share one definition. ``fbgcomp_display`` is the headless "display" program
of the simulated machine in ``examples/linuxcnc``. See docs/linuxcnc.md.
"""
