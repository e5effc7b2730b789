// The load tester only ever targets this machine: a gRPC target is accepted when its host
// resolves to loopback addresses only (127.0.0.0/8, ::1, IPv4-mapped 127.x), or when it is a
// Unix domain socket.
#pragma once

#include <string>

namespace placedb::client {

// The host part of a gRPC target: "localhost:50051" -> "localhost", "[::1]:1" -> "::1",
// "dns:///h:1" -> "h", "ipv4:127.0.0.1:1" -> "127.0.0.1". Empty for Unix sockets ("unix:...").
std::string TargetHost(const std::string& target, bool* unix_socket);

// True when every address `target`'s host resolves to is a loopback address. Otherwise false and
// *why says which address is not, or that the host does not resolve.
bool IsLoopbackTarget(const std::string& target, std::string* why);

}  // namespace placedb::client
