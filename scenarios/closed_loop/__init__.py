"""One closed-loop run: scenarios, the loop, the runner and its metrics."""
