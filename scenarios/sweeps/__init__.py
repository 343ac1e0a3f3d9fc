"""Many runs: resumable sweeps on a process pool or on Ray, one per results folder."""
