"""Running nodes together: process launch, DDS environment, live runs and bag output."""
