"""Where readings go beyond the command's own output: metrics, line protocol, MQTT."""
