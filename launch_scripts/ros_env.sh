#!/usr/bin/env bash
# Loopback-only DDS settings; sourced by every launch script and by the tests.
# Traffic must never leave this machine: discovery is limited to localhost, the Fast DDS profile
# whitelists 127.0.0.1 and gives shared memory a 32 MiB segment, and each run gets its own domain.
# NRSFM_DDS=network (the graph across hosts, README "Scaling"): discovery is left to the
# environment (ROS_AUTOMATIC_DISCOVERY_RANGE default SUBNET, ROS_STATIC_PEERS, the profile, and
# ROS_DOMAIN_ID, default 0: the same on every host).
_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
if [ "${NRSFM_DDS:-loopback}" = network ]; then
  export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-SUBNET}"
else
  export FASTRTPS_DEFAULT_PROFILES_FILE="${FASTRTPS_DEFAULT_PROFILES_FILE:-$_root/config/fastdds_loopback.xml}"
  export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
  export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( ($$ % 90) + 10 ))}"
fi
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# One BLAS thread per process (users may override): the solves are many small products, and on
# 2 cores two OpenBLAS threads made a process spend 7x the CPU time (fleet bench) and the
# reconstructor's 60-frame flush take 1.2-3.7 s instead of 0.12 s.
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
