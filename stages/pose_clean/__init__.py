"""Pose cleaning: Eq. 4 jump outliers, Kalman (causal and RTS) and EgoCap smoothing."""
