"""The HIL session: the ECU-side processes and the HIL block of the summary."""
