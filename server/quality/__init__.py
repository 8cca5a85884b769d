"""Quality: what each spray run measured, and whether its part is good.

After a spray run's path (the trajectory operation) the cell measures how it
went from what the devices and the camera reported, and inspects the part:

- trajectory precision: the robot's sampled positions against the planned
  spray segments;
- dispensing consistency: the dispenser's flow readings against the setpoint,
  and the glue dispensed against what the path needed;
- vision accuracy: the calibration markers re-detected on the run's frame
  against the stored calibration, and the workpiece's match score;
- the bead: found in a frame taken after the run along each planned segment,
  its width, gaps and offset measured against tolerances (settings).

The run's result carries a summary under "inspection" (so the run record, the
run-end listeners and the KPIs see it); the whole inspection and its annotated
image are kept per run (GET /runs/{id}/inspection, /inspection.jpg). A run
that did not complete, or ran with inspection_enabled off, has no inspection.
"""
