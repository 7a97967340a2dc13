"""The peers: the systems users would pick instead of clothbench, each written as its users
would write it, run in the same harness as clothbench's own backends."""
