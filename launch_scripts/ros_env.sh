#!/usr/bin/env bash
# Loopback-only DDS settings; sourced by every launch script and by the tests.
# Traffic must never leave this machine: discovery is limited to localhost, the Fast DDS profile
# whitelists 127.0.0.1 and gives shared memory a 32 MiB segment, and each run gets its own domain.
_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export FASTRTPS_DEFAULT_PROFILES_FILE="${FASTRTPS_DEFAULT_PROFILES_FILE:-$_root/config/fastdds_loopback.xml}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( ($$ % 90) + 10 ))}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
