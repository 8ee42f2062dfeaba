"""Hardware: servo controllers, position trackers, data collection, simulated devices."""
