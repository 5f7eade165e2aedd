// A CAN bus inside one process: every attached node receives every other node's frames,
// on its own io_context.
#include <algorithm>
#include <atomic>
#include <mutex>

#include <boost/asio/post.hpp>

#include "fettle/drivers/canopen_transport.hpp"

namespace fettle::canopen {

namespace {

class BusNode;

}  // namespace

struct InProcessBus::Impl {
  std::mutex mutex;
  std::vector<std::weak_ptr<BusNode>> nodes;
  std::atomic<bool> connected{true};
  std::atomic<std::uint64_t> sent{0};
  void deliver(const BusNode* from, const CanFrame& f);
};

namespace {

class BusNode : public CanTransport, public std::enable_shared_from_this<BusNode> {
 public:
  BusNode(boost::asio::io_context& io, std::shared_ptr<InProcessBus::Impl> bus, std::string name)
      : io_(io), bus_(std::move(bus)), name_(std::move(name)) {}

  void start(FrameHandler on_frame, ErrorHandler on_error) override {
    on_frame_ = std::move(on_frame);
    on_error_ = std::move(on_error);
  }
  void send(const CanFrame& frame) override {
    if (closed_) return;
    if (auto bus = bus_.lock()) bus->deliver(this, frame);
  }
  void close() override {
    closed_ = true;
    on_frame_ = nullptr;
    on_error_ = nullptr;
  }
  [[nodiscard]] std::string name() const override { return "bus:" + name_; }

  void receive(const CanFrame& f) {
    boost::asio::post(io_, [weak = weak_from_this(), f] {
      if (auto self = weak.lock())
        if (!self->closed_ && self->on_frame_) self->on_frame_(f);
    });
  }

 private:
  boost::asio::io_context& io_;
  std::weak_ptr<InProcessBus::Impl> bus_;
  std::string name_;
  FrameHandler on_frame_;
  ErrorHandler on_error_;
  std::atomic<bool> closed_{false};
};

}  // namespace

void InProcessBus::Impl::deliver(const BusNode* from, const CanFrame& f) {
  if (!connected) return;
  ++sent;
  std::vector<std::shared_ptr<BusNode>> targets;
  {
    std::lock_guard lock(mutex);
    std::erase_if(nodes, [](const auto& w) { return w.expired(); });
    for (const auto& w : nodes)
      if (auto n = w.lock(); n && n.get() != from) targets.push_back(std::move(n));
  }
  for (const auto& n : targets) n->receive(f);
}

InProcessBus::InProcessBus() : impl_(std::make_shared<Impl>()) {}

std::shared_ptr<InProcessBus> InProcessBus::create() { return std::shared_ptr<InProcessBus>(new InProcessBus()); }

std::shared_ptr<CanTransport> InProcessBus::attach(boost::asio::io_context& io, std::string name) {
  auto node = std::make_shared<BusNode>(io, impl_, std::move(name));
  std::lock_guard lock(impl_->mutex);
  impl_->nodes.push_back(node);
  return node;
}

void InProcessBus::set_connected(bool connected) { impl_->connected = connected; }

std::uint64_t InProcessBus::frames_sent() const { return impl_->sent; }

}  // namespace fettle::canopen
