"""One planning process of :func:`erva_ros.core.loop.warmup.warm`: a target in, its plan out.

``python -m erva_ros.core.loop.plan_worker TARGET_FILE PLAN_FILE``: the target pickled in
the first file, its :class:`~erva_ros.core.model.codegen.Plan` pickled into the second.  A
fresh process per target (no warm caches), in a session of its own: Ctrl-C is the
parent's, which ends it (:func:`erva_ros.core.model.codegen.stop_compilers`).
"""

import pickle
import sys

from erva_ros.core.loop.warmup import plan_target


def main(argv) -> int:
    """Plan the target of ``argv[0]`` into ``argv[1]``."""
    source, destination = argv
    with open(source, 'rb') as fh:
        target = pickle.load(fh)
    plan = plan_target(target)
    with open(destination, 'wb') as fh:
        pickle.dump(plan, fh, protocol=pickle.HIGHEST_PROTOCOL)
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
