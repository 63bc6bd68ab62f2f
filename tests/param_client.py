"""A separate rclpy process that reads or sets parameters of a node over its services.

    python param_client.py get NODE NAME [NAME ...]   prints {name: value} as JSON
    python param_client.py set NODE NAME VALUE [NAME VALUE ...]
                                  each VALUE a Python literal, each set a request of its own,
                                  in order; prints a line per set: 'ok' or 'rejected: <reason>'
Exit 0 when the calls were answered. Used through conftest.get_params / set_param / set_params.
"""
import ast
import json
import sys

import rclpy
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.parameter import Parameter, parameter_value_to_python


def call(node, srv_type, service: str, request):
    client = node.create_client(srv_type, service)
    if not client.wait_for_service(timeout_sec=30):
        print("no service")
        sys.exit(1)
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=20)
    return future.result()


def main():
    verb, node_name, args = sys.argv[1], sys.argv[2], sys.argv[3:]
    rclpy.init()
    node = rclpy.create_node("test_param_client")
    if verb == "get":
        result = call(node, GetParameters, f"{node_name}/get_parameters",
                      GetParameters.Request(names=args))
        values = [parameter_value_to_python(v) for v in result.values]
        print(json.dumps(dict(zip(args, values))), flush=True)
    else:
        for name, text in zip(args[::2], args[1::2]):
            request = SetParameters.Request(
                parameters=[Parameter(name, value=ast.literal_eval(text)).to_parameter_msg()])
            result = call(node, SetParameters, f"{node_name}/set_parameters", request).results[0]
            print("ok" if result.successful else f"rejected: {result.reason}", flush=True)
    rclpy.shutdown()


if __name__ == "__main__":
    main()
