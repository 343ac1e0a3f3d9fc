"""The equations of motion, one function per backend (numpy, CasADi, compiled), and the simulator."""
