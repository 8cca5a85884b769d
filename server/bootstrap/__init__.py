"""The composition root: turns Settings into running devices and a commissioned cell.

It is the one layer that may know both the drivers and the core (`CellDevices`,
the operations), so that neither has to know the other: drivers stay plain
device clients and simulators, and the core receives finished devices.
`server/bootstrap/cell.py` calls it when the cell starts.
"""
