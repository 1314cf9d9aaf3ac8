"""Results: per-class metrics, the run's SQLite store, mIoU maps and replaying stored rows."""
