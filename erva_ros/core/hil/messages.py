"""The ECU's CAN frames as the HIL topics' messages (erva_ros/core/hil/topics.py), no ROS.

ecu_bridge_node publishes each ECU frame as soon as it arrives, on its own topic, stamped
with the CAN receive time of its ECU cycle's first frame, and each whole cycle once more
on ``ecu/measurements`` (NaN for a lost frame's values).  :class:`EcuMessages` turns the
bridge core's frames and cycles into those messages' CDR bytes.
"""

import math
from typing import List, Tuple

from erva_ros.core import contract, topics
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.hil.bridge import EcuCycle, SensorFrame
from erva_ros.core.hil.codec import Kind
from erva_ros.core.model.hardware import GeneratorHardware

NAN = math.nan


class EcuMessages:
    """Encode ECU frames and cycles; ``arm_m`` is the ball-screw arm l (v_gen = l·φ')."""

    def __init__(self, hardware: GeneratorHardware, arm_m: float):
        self.hw, self.arm_m = hardware, arm_m
        self._applied = contract.JointStateEncoder(hil_topics.APPLIED_JOINTS)
        self._suspension = contract.JointStateEncoder((hil_topics.SUSPENSION_JOINT,))
        self._generator = contract.JointStateEncoder((topics.GENERATOR_JOINT,))

    def frame(self, f: SensorFrame) -> List[Tuple[str, bytes]]:
        """Return [(topic, bytes)] of one frame, stamped with its cycle's stamp."""
        stamp, p = int(round(f.stamp * 1e9)), f.payload
        if f.kind is Kind.STATUS:
            return [(hil_topics.ECU_DAMPING_APPLIED, self._applied.encode(
                stamp, (float(p.c_e_applied), float(p.c_e_mean))))]
        if f.kind is Kind.CHASSIS:
            return [(hil_topics.ECU_SPRUNG_ACCEL, contract.encode_accel(stamp,
                                                                        float(p.sprung_accel))),
                    (hil_topics.ECU_SUSPENSION, self._suspension.encode(
                        stamp, (float(p.deflection),)))]
        # The contract's generator topic is in stroke terms: v_gen = l·φ'.
        return [(hil_topics.ECU_GENERATOR, self._generator.encode(
            stamp, (), (float(p.speed * self.arm_m),),
            (float(self.hw.force_from_current(p.current)),)))]

    def cycle(self, cyc: EcuCycle) -> bytes:
        """Return one ECU cycle as ``ecu/measurements`` (NaN: that frame was lost)."""
        st, ch, gen = (cyc.payloads.get(k)
                       for k in (Kind.STATUS, Kind.CHASSIS, Kind.GENERATOR))
        values = ([float(st.c_e_applied), float(st.c_e_mean)] if st else [NAN, NAN]) + (
            [float(ch.sprung_accel), float(ch.deflection)] if ch else [NAN, NAN]) + (
            [float(gen.speed), float(self.hw.force_from_current(gen.current))]
            if gen else [NAN, NAN])
        return contract.MEASUREMENTS_ENCODER.encode(int(round(cyc.stamp * 1e9)), values)


__all__ = ['EcuMessages']
