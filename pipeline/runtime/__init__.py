"""Host and process: code versions, device and precision, the environment record, error types, progress."""
