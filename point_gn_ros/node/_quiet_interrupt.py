"""Imported first by the node program: Ctrl-C during its slow imports exits without a traceback.

Only when this process *is* the node (`classifier_node` console script or
`python -m point_gn_ros.node.classifier_node`), never when a test or tool imports the module.
`classifier_node.main()` restores Python's handler before rclpy installs its own.
"""

from pathlib import Path
import signal
import sys

if sys.argv and Path(sys.argv[0]).stem == 'classifier_node':
    signal.signal(signal.SIGINT, signal.SIG_DFL)
