"""``python -m fbgcomp.runtime.outputs.opcua --worker-fd FD``: the OPC UA server process.

Started by serve (:class:`~fbgcomp.runtime.outputs.opcua.bridge.OpcUaServer`), never by hand.
"""

from fbgcomp.runtime.outputs.opcua.worker import main

if __name__ == "__main__":
    main()
