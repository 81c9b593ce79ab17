# Environment for running erva_ros from the project venv (sourced by .ci/erva and .ci/run).
# DDS stays on this machine; ament_index finds the wheels' share/ via the venv prefix.
venv="${ERVA_VENV:-$root/.venv}"
export PATH="$venv/bin:$PATH"
export AMENT_PREFIX_PATH="$venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( ($$ % 100) + 100 ))}"
export MPLBACKEND=Agg
