"""Fieldbus drivers: base (ABC, errors), modbus_tcp, canopen, virtual."""
