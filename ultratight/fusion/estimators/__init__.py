"""Generic estimators: KF/EKF/UKF/AUKF/CKF/SRCKF, their adaptive (AKF, IAKF, AFF/AFM) and
robust (chi-square + Newton) parts, the quaternion AUKF, and the covariance guards they share."""
