"""fbgcomp: compensate machine-tool structural deformations from FBG sensors.

Data flow: optics -> structure -> kinematics -> models -> runtime, with io (campaign),
cli and report at the edges. See docs/architecture.md.
"""

# The one place the version is written: pyproject.toml reads it (dynamic version), model files and
# the twin cache record it.
__version__ = "0.1.0"
