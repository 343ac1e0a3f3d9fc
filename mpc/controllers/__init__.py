"""The controllers (LQR, LTV-MPC, SQP, NMPC), their QP solvers, timing rules and readiness."""
