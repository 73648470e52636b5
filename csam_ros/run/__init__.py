"""The csam command's pipelines: the offline replay, the live demo and replay with nodes, data
set import, calibration and evaluation; and running nodes together: process launch, DDS
environment, hosts, live runs and bag output."""
