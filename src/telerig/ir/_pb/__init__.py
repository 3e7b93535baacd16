"""Generated protobuf code for the schemas in telerig/ir/proto/telerig/v1; regenerate with `python -m telerig.ir.protogen`."""
