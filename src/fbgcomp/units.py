"""Names and units shared by every stage: the TTP axes and their column names.

TTP displacements are in µm throughout (``_um``); the axes are named as in the paper and the
campaign files.
"""

#: The tool-tip point's deviation axes, in the order every array and table uses.
AXES = ("dx", "dy", "dz")

#: The interferometer's (reference instrument's) column of each axis in a campaign, in µm.
REFERENCE_COLUMNS = tuple(f"{a}_um" for a in AXES)
