"""Scenarios: a load (UAV mission, replayed DJI flight, HPPC), a truth cell, the lab schedule and a sensor model.

``load_scenario(name_or_path) -> Scenario``, ``scenario_names()``; ``Scenario.realize(seeds)`` returns the measured
batch with the true SOC, ``characterisation(seed)`` the HPPC of the same truth cell, ``initial_soc(seeds)`` the SOC
guesses and ``sensor_noise()`` the white-noise SDs for the estimators. One idea per module:

mission.py    momentum-theory multirotor mission drawn as a constant-power load
schedule.py   CC-CV charge, rest, load until UV
replay.py     real DJI M100 flight current (or its derived template) at C-rate
sensors.py    noise, offset, gain, drift, ADC, dropouts, stuck-at, jitter; initial-SOC and capacity errors
truth.py      the truth cell (2 RC, hysteresis, Arrhenius, thermal, Butler–Volmer)
scenario.py   the Scenario object; catalog.py the TOML catalog in catalog/
"""

from .catalog import load_scenario, scenario_names
from .scenario import Scenario, ScenarioSpec
from .sensors import Channel, Fault, SensorSpec
from .truth import TruthCell, TruthParams

__all__ = ["load_scenario", "scenario_names", "Scenario", "ScenarioSpec", "SensorSpec", "Channel", "Fault",
           "TruthCell", "TruthParams"]
