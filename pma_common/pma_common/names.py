"""The names of the project's topics, services and actions, relative to a muscle's namespace.

Every node, the CLI, the live view, the recorder's defaults and the tests take them from here,
so a rename is one line. Relative names (REP-144 style), so `-r __ns:=/left` moves a whole
muscle; `/diagnostics` is the ROS-wide aggregate and stays absolute. docs/driver.md,
docs/model.md and docs/control.md describe what each carries.
"""

# The driver (pma_driver driver_node)
STATE = 'pma/state'                          # pma_interfaces/msg/PmaState, every sample
PRESSURE = 'pma/pressure'                    # sensor_msgs/msg/FluidPressure (absolute)
RANGE = 'pma/range'                          # sensor_msgs/msg/Range (the HC-SR04)
PRESSURE_SETPOINT = 'pma/pressure_setpoint'  # std_msgs/msg/Float64, gauge [Pa], in
SWEEP = 'pma/sweep'                          # pma_interfaces/action/Sweep
SWEEP_RECORD = 'pma/sweep_record'            # pma_interfaces/msg/SweepRecord, latched
COMMANDER_LEASE = 'pma/commander_lease'      # pma_interfaces/msg/CommanderLease, in

# The model (pma_model model_node)
PREDICTION = 'pma/prediction'                # pma_interfaces/msg/PmaPrediction
MODEL_PARAMS = 'pma/model_params'            # pma_interfaces/msg/ModelParams, latched
PRESSURE_FOR_LENGTH = 'pressure_for_length'  # pma_interfaces/srv/PressureForLength

# The length controller (pma_control length_controller)
CONTROL_STATE = 'pma/control_state'          # pma_interfaces/msg/ControlState
LENGTH_SETPOINT = 'pma/length_setpoint'      # pma_interfaces/msg/LengthSetpoint, in
MOVE_TO_LENGTH = 'pma/move_to_length'        # pma_interfaces/action/MoveToLength

DIAGNOSTICS = '/diagnostics'                 # diagnostic_msgs/msg/DiagnosticArray

# What the recorder writes by default: every topic above (the actions' own topics aside).
RECORDED = (STATE, PRESSURE, RANGE, PREDICTION, MODEL_PARAMS, CONTROL_STATE, PRESSURE_SETPOINT,
            LENGTH_SETPOINT, SWEEP_RECORD, COMMANDER_LEASE, DIAGNOSTICS)
