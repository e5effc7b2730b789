#include "client/loopback.h"

#include <arpa/inet.h>
#include <netdb.h>
#include <netinet/in.h>
#include <sys/socket.h>

#include <cstring>

namespace placedb::client {

namespace {

bool StartsWith(const std::string& text, const std::string& prefix) {
  return text.compare(0, prefix.size(), prefix) == 0;
}

}  // namespace

std::string TargetHost(const std::string& target, bool* unix_socket) {
  *unix_socket = false;
  std::string rest = target;
  if (StartsWith(rest, "unix:") || StartsWith(rest, "unix-abstract:")) {
    *unix_socket = true;
    return "";
  }
  for (const char* scheme : {"dns:///", "dns:", "ipv4:", "ipv6:"}) {
    if (StartsWith(rest, scheme)) {
      rest = rest.substr(std::strlen(scheme));
      break;
    }
  }
  // dns://AUTHORITY/host:port: drop the authority (the resolver, not the target).
  if (StartsWith(rest, "//")) {
    const auto slash = rest.find('/', 2);
    rest = slash == std::string::npos ? "" : rest.substr(slash + 1);
  }
  // ipv4:/ipv6: targets may list several addresses separated by commas: the caller checks each
  // by calling again; here the first one is taken.
  if (const auto comma = rest.find(','); comma != std::string::npos) rest = rest.substr(0, comma);
  if (StartsWith(rest, "[")) {
    const auto close = rest.find(']');
    return close == std::string::npos ? rest.substr(1) : rest.substr(1, close - 1);
  }
  const auto first = rest.find(':');
  if (first == std::string::npos) return rest;
  if (rest.find(':', first + 1) != std::string::npos) return rest;  // a bare IPv6 literal
  return rest.substr(0, first);
}

bool IsLoopbackTarget(const std::string& target, std::string* why) {
  // Several comma-separated addresses (ipv4:a:1,b:2): every one must be loopback.
  std::string scheme;
  for (const char* s : {"ipv4:", "ipv6:"}) {
    if (StartsWith(target, s)) scheme = s;
  }
  if (!scheme.empty() && target.find(',') != std::string::npos) {
    std::string list = target.substr(scheme.size());
    size_t start = 0;
    while (start <= list.size()) {
      const auto comma = list.find(',', start);
      const std::string one = list.substr(start, comma - start);
      if (!IsLoopbackTarget(scheme + one, why)) return false;
      if (comma == std::string::npos) break;
      start = comma + 1;
    }
    return true;
  }

  bool unix_socket = false;
  const std::string host = TargetHost(target, &unix_socket);
  if (unix_socket) return true;
  if (host.empty()) {
    *why = "'" + target + "' names no host";
    return false;
  }
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* found = nullptr;
  if (const int rc = getaddrinfo(host.c_str(), nullptr, &hints, &found); rc != 0) {
    *why = "cannot resolve '" + host + "': " + gai_strerror(rc);
    return false;
  }
  bool any = false;
  bool all_loopback = true;
  for (const addrinfo* a = found; a != nullptr; a = a->ai_next) {
    char text[INET6_ADDRSTRLEN] = "?";
    bool loopback = false;
    if (a->ai_family == AF_INET) {
      const auto* v4 = reinterpret_cast<const sockaddr_in*>(a->ai_addr);
      const uint32_t address = ntohl(v4->sin_addr.s_addr);
      loopback = (address >> 24) == 127;
      inet_ntop(AF_INET, &v4->sin_addr, text, sizeof text);
    } else if (a->ai_family == AF_INET6) {
      const auto* v6 = reinterpret_cast<const sockaddr_in6*>(a->ai_addr);
      const in6_addr& address = v6->sin6_addr;
      loopback = IN6_IS_ADDR_LOOPBACK(&address) ||
                 (IN6_IS_ADDR_V4MAPPED(&address) && address.s6_addr[12] == 127);
      inet_ntop(AF_INET6, &address, text, sizeof text);
    } else {
      continue;
    }
    any = true;
    if (!loopback) {
      all_loopback = false;
      *why = "'" + host + "' resolves to " + text + ", which is not a loopback address";
      break;
    }
  }
  freeaddrinfo(found);
  if (!any) {
    *why = "'" + host + "' resolves to no IPv4 or IPv6 address";
    return false;
  }
  return all_loopback;
}

}  // namespace placedb::client
