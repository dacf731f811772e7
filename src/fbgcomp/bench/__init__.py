"""Virtual test bench: scenarios on the FE twin measured by simulated instruments, and synthetic campaigns."""
