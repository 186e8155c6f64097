"""Pure physics: kinematics, statics, pulley friction and the sensor chain. No I/O."""
