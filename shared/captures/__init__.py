"""Recordings in the containers the devices' own tools write (issue 51), read into the packets and CAN
frames the live adapters take.

Layers, lowest first:
- `errors`: the typed exceptions (a fatal `CaptureError` names the file and the offset or index);
- `pcap`: pcap / pcapng captures (tcpdump, Wireshark, RSView, VeloView) -> UDP datagrams, through dpkt;
- `canlog`: CAN logs (candump -L, Vector ASC / BLF) -> CAN frames, through python-can's LogReader;
- `identify`: which device a unit's packets come from, by their bytes;
- `units`: a unit's packets or frames -> the project's sensor messages, through the live adapters'
  decoders (Robosense `LidarStream`, Velodyne `VelodyneStream`, ARS 408 `ListAssembler`);
- `importer`: a capture or log into the project's recording (`rmmdet import`), and `replay`: a capture
  sent to a site's devices' ports and buses at its recorded timing (`rmmdet devices replay`).
"""
