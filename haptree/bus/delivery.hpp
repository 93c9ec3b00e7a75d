// Pausing a raw subscription's delivery while the bus runs (the coupler's second-writer check, issue
// 15.1): while stopped, the channel's messages wake no handler thread (LCM drops them on arrival).
#pragma once

#include <mutex>

#include "haptree/bus/bus.hpp"

namespace haptree::bus {

// Stops (on = false) or resumes sub's delivery: an LCM unsubscribe / subscribe; the Subscription and its
// counters stay. Any thread except a handler's; resuming allocates. A dispatch already under way on the
// handler thread may still deliver one message after a stop (LCM's C library frees the handler only
// when that dispatch returns; the Subscription outlives it). Serialised with Bus::subscribe_raw by delivery_mutex() (lcm::LCM's list of
// subscriptions is not thread-safe); typed subscriptions are made before the bus runs.
void set_delivery(Bus& bus, RawSubscription& sub, bool on);
std::mutex& delivery_mutex();

}  // namespace haptree::bus
