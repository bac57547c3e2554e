"""Autopilots' own logs: ArduPilot DataFlash (binary .bin, text .log) and PX4 ULog (.ulg).

detect     what a file is, by its content
dataflash  the DataFlash reader: one compiled pass indexes the records, numpy views them
ulog       the ULog reader (pyulog, only the topics asked for)
presets    per autopilot, which message or topic gives each channel, in which units
content    what a preset finds: signals, vehicle, airborne times
reader     read_log(path, config) -> (Recording, account)
"""
