"""Generated protobuf code for telerig/v1/ir.proto; regenerate with `python -m telerig.ir.protogen`."""
