// The GenICam description of the simulated 3D camera, served by Aravis' ArvGvFakeCamera.
//
// Register addresses below 0x200 and 0x300..0x30c are the ones ArvGvFakeCamera itself
// implements (arvfakecamera.h: Width 0x100, PixelFormat 0x128, TriggerMode 0x300, ...);
// the Scan3d block at 0xA000 (manufacturer-specific space) is written by SimulatedCamera.
// Features follow the GenICam SFNC names (Scan3dControl) so the driver reads them exactly
// as it reads a real structured-light camera's.
#include "camera_internal.hpp"

namespace fettle::sim::detail {

const char* const kCameraGenicamXml = R"xml(<?xml version="1.0" encoding="utf-8"?>
<RegisterDescription ModelName="FettleSim3D" VendorName="Fettle" StandardNameSpace="None"
    SchemaMajorVersion="1" SchemaMinorVersion="0" SchemaSubMinorVersion="1"
    MajorVersion="1" MinorVersion="0" SubMinorVersion="0"
    ToolTip="Fettle simulated structured-light 3D camera" ProductGuid="0" VersionGuid="0"
    xmlns="http://www.genicam.org/GenApi/Version_1_0"
    xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"
    xsi:schemaLocation="http://www.genicam.org/GenApi/Version_1_0 GenApiSchema.xsd">

  <Category Name="Root" NameSpace="Standard">
    <pFeature>DeviceControl</pFeature>
    <pFeature>ImageFormatControl</pFeature>
    <pFeature>AcquisitionControl</pFeature>
    <pFeature>Scan3dControl</pFeature>
    <pFeature>TransportLayerControl</pFeature>
  </Category>

  <!-- Device control: strings of the GigE Vision bootstrap registers -->
  <Category Name="DeviceControl" NameSpace="Standard">
    <pFeature>DeviceVendorName</pFeature>
    <pFeature>DeviceModelName</pFeature>
    <pFeature>DeviceManufacturerInfo</pFeature>
    <pFeature>DeviceVersion</pFeature>
    <pFeature>DeviceSerialNumber</pFeature>
    <pFeature>DeviceID</pFeature>
  </Category>
  <StringReg Name="DeviceVendorName" NameSpace="Standard">
    <Address>0x48</Address><Length>32</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
  </StringReg>
  <StringReg Name="DeviceModelName" NameSpace="Standard">
    <Address>0x68</Address><Length>32</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
  </StringReg>
  <StringReg Name="DeviceVersion" NameSpace="Standard">
    <Address>0x88</Address><Length>32</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
  </StringReg>
  <StringReg Name="DeviceManufacturerInfo" NameSpace="Standard">
    <Address>0xa8</Address><Length>48</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
  </StringReg>
  <StringReg Name="DeviceSerialNumber" NameSpace="Standard">
    <Address>0xd8</Address><Length>16</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
  </StringReg>
  <StringReg Name="DeviceID" NameSpace="Standard">
    <Address>0xd8</Address><Length>16</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
  </StringReg>

  <!-- Image format: the range map's size is fixed by the simulated sensor -->
  <Category Name="ImageFormatControl" NameSpace="Standard">
    <pFeature>SensorWidth</pFeature>
    <pFeature>SensorHeight</pFeature>
    <pFeature>Width</pFeature>
    <pFeature>Height</pFeature>
    <pFeature>OffsetX</pFeature>
    <pFeature>OffsetY</pFeature>
    <pFeature>PixelFormat</pFeature>
  </Category>
  <IntReg Name="SensorWidth" NameSpace="Standard">
    <Address>0x11c</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <IntReg Name="SensorHeight" NameSpace="Standard">
    <Address>0x118</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <IntReg Name="Width" NameSpace="Standard">
    <Address>0x100</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <IntReg Name="Height" NameSpace="Standard">
    <Address>0x104</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <IntReg Name="OffsetX" NameSpace="Standard">
    <Address>0x130</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <IntReg Name="OffsetY" NameSpace="Standard">
    <Address>0x134</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Enumeration Name="PixelFormat" NameSpace="Standard">
    <EnumEntry Name="Coord3D_C16" NameSpace="Standard"><Value>17825976</Value></EnumEntry>
    <EnumEntry Name="Coord3D_C32f" NameSpace="Standard"><Value>18874559</Value></EnumEntry>
    <EnumEntry Name="Coord3D_ABC32f" NameSpace="Standard"><Value>39846080</Value></EnumEntry>
    <EnumEntry Name="Mono8" NameSpace="Standard"><Value>17301505</Value></EnumEntry>
    <pValue>PixelFormatRegister</pValue>
  </Enumeration>
  <IntReg Name="PixelFormatRegister" NameSpace="Custom">
    <Address>0x128</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>

  <!-- Acquisition: continuous acquisition, one frame per software trigger -->
  <Category Name="AcquisitionControl" NameSpace="Standard">
    <pFeature>AcquisitionMode</pFeature>
    <pFeature>AcquisitionStart</pFeature>
    <pFeature>AcquisitionStop</pFeature>
    <pFeature>TriggerSelector</pFeature>
    <pFeature>TriggerMode</pFeature>
    <pFeature>TriggerSource</pFeature>
    <pFeature>TriggerSoftware</pFeature>
    <pFeature>ExposureTime</pFeature>
  </Category>
  <Enumeration Name="AcquisitionMode" NameSpace="Standard">
    <EnumEntry Name="Continuous" NameSpace="Standard"><Value>1</Value></EnumEntry>
    <pValue>AcquisitionModeRegister</pValue>
  </Enumeration>
  <IntReg Name="AcquisitionModeRegister" NameSpace="Custom">
    <Address>0x12c</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Command Name="AcquisitionStart" NameSpace="Standard">
    <pValue>AcquisitionCommandRegister</pValue><CommandValue>1</CommandValue>
  </Command>
  <Command Name="AcquisitionStop" NameSpace="Standard">
    <pValue>AcquisitionCommandRegister</pValue><CommandValue>0</CommandValue>
  </Command>
  <IntReg Name="AcquisitionCommandRegister" NameSpace="Custom">
    <Address>0x124</Address><Length>4</Length><AccessMode>WO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Enumeration Name="TriggerSelector" NameSpace="Standard">
    <EnumEntry Name="FrameStart" NameSpace="Standard"><Value>0</Value></EnumEntry>
    <pValue>TriggerSelectorValue</pValue>
  </Enumeration>
  <Integer Name="TriggerSelectorValue" NameSpace="Custom"><Value>0</Value></Integer>
  <Enumeration Name="TriggerMode" NameSpace="Standard">
    <EnumEntry Name="Off" NameSpace="Standard"><Value>0</Value></EnumEntry>
    <EnumEntry Name="On" NameSpace="Standard"><Value>1</Value></EnumEntry>
    <pValue>TriggerModeRegister</pValue>
  </Enumeration>
  <IntReg Name="TriggerModeRegister" NameSpace="Custom">
    <Address>0x300</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Enumeration Name="TriggerSource" NameSpace="Standard">
    <EnumEntry Name="Line0" NameSpace="Standard"><Value>0</Value></EnumEntry>
    <EnumEntry Name="Software" NameSpace="Standard"><Value>1</Value></EnumEntry>
    <pValue>TriggerSourceRegister</pValue>
  </Enumeration>
  <IntReg Name="TriggerSourceRegister" NameSpace="Custom">
    <Address>0x304</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Command Name="TriggerSoftware" NameSpace="Standard">
    <pValue>TriggerSoftwareRegister</pValue><CommandValue>1</CommandValue>
  </Command>
  <IntReg Name="TriggerSoftwareRegister" NameSpace="Custom">
    <Address>0x30c</Address><Length>4</Length><AccessMode>WO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Float Name="ExposureTime" NameSpace="Standard">
    <pValue>ExposureTimeConverter</pValue><Min>10.0</Min><Max>1000000.0</Max><Unit>us</Unit>
  </Float>
  <Converter Name="ExposureTimeConverter" NameSpace="Custom">
    <FormulaTo>FROM</FormulaTo><FormulaFrom>TO</FormulaFrom><pValue>ExposureTimeRegister</pValue>
  </Converter>
  <IntReg Name="ExposureTimeRegister" NameSpace="Custom">
    <Address>0x120</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>

  <!-- Scan3d (GenICam SFNC 3D): a rectified range map, Z = raw * scale + offset, in mm -->
  <Category Name="Scan3dControl" NameSpace="Standard">
    <pFeature>Scan3dDistanceUnit</pFeature>
    <pFeature>Scan3dCoordinateSystem</pFeature>
    <pFeature>Scan3dOutputMode</pFeature>
    <pFeature>Scan3dCoordinateSystemReference</pFeature>
    <pFeature>Scan3dCoordinateSelector</pFeature>
    <pFeature>Scan3dCoordinateScale</pFeature>
    <pFeature>Scan3dCoordinateOffset</pFeature>
    <pFeature>Scan3dInvalidDataFlag</pFeature>
    <pFeature>Scan3dInvalidDataValue</pFeature>
    <pFeature>Scan3dAxisMin</pFeature>
    <pFeature>Scan3dAxisMax</pFeature>
    <pFeature>Scan3dFocalLength</pFeature>
    <pFeature>Scan3dPrincipalPointU</pFeature>
    <pFeature>Scan3dPrincipalPointV</pFeature>
  </Category>
  <Enumeration Name="Scan3dDistanceUnit" NameSpace="Standard">
    <EnumEntry Name="Millimeter" NameSpace="Standard"><Value>0</Value></EnumEntry>
    <pValue>Scan3dDistanceUnitValue</pValue>
  </Enumeration>
  <Integer Name="Scan3dDistanceUnitValue" NameSpace="Custom"><Value>0</Value></Integer>
  <Enumeration Name="Scan3dCoordinateSystem" NameSpace="Standard">
    <EnumEntry Name="Cartesian" NameSpace="Standard"><Value>0</Value></EnumEntry>
    <pValue>Scan3dCoordinateSystemValue</pValue>
  </Enumeration>
  <Integer Name="Scan3dCoordinateSystemValue" NameSpace="Custom"><Value>0</Value></Integer>
  <Enumeration Name="Scan3dOutputMode" NameSpace="Standard">
    <EnumEntry Name="RectifiedC" NameSpace="Standard"><Value>3</Value></EnumEntry>
    <pValue>Scan3dOutputModeValue</pValue>
  </Enumeration>
  <Integer Name="Scan3dOutputModeValue" NameSpace="Custom"><Value>3</Value></Integer>
  <Enumeration Name="Scan3dCoordinateSystemReference" NameSpace="Standard">
    <EnumEntry Name="Anchor" NameSpace="Standard"><Value>0</Value></EnumEntry>
    <pValue>Scan3dCoordinateSystemReferenceValue</pValue>
  </Enumeration>
  <Integer Name="Scan3dCoordinateSystemReferenceValue" NameSpace="Custom"><Value>0</Value></Integer>
  <Enumeration Name="Scan3dCoordinateSelector" NameSpace="Standard">
    <EnumEntry Name="CoordinateC" NameSpace="Standard"><Value>2</Value></EnumEntry>
    <pValue>Scan3dCoordinateSelectorValue</pValue>
  </Enumeration>
  <Integer Name="Scan3dCoordinateSelectorValue" NameSpace="Custom"><Value>2</Value></Integer>
  <FloatReg Name="Scan3dCoordinateScale" NameSpace="Standard">
    <Address>0xA000</Address><Length>8</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Endianess>BigEndian</Endianess>
  </FloatReg>
  <FloatReg Name="Scan3dCoordinateOffset" NameSpace="Standard">
    <Address>0xA008</Address><Length>8</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Endianess>BigEndian</Endianess>
  </FloatReg>
  <Boolean Name="Scan3dInvalidDataFlag" NameSpace="Standard">
    <pValue>Scan3dInvalidDataFlagRegister</pValue><OnValue>1</OnValue><OffValue>0</OffValue>
  </Boolean>
  <IntReg Name="Scan3dInvalidDataFlagRegister" NameSpace="Custom">
    <Address>0xA010</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <FloatReg Name="Scan3dInvalidDataValue" NameSpace="Standard">
    <Address>0xA018</Address><Length>8</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Endianess>BigEndian</Endianess>
  </FloatReg>
  <FloatReg Name="Scan3dAxisMin" NameSpace="Standard">
    <Address>0xA020</Address><Length>8</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Endianess>BigEndian</Endianess>
  </FloatReg>
  <FloatReg Name="Scan3dAxisMax" NameSpace="Standard">
    <Address>0xA028</Address><Length>8</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Endianess>BigEndian</Endianess>
  </FloatReg>
  <FloatReg Name="Scan3dFocalLength" NameSpace="Standard">
    <Address>0xA030</Address><Length>8</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Endianess>BigEndian</Endianess>
  </FloatReg>
  <FloatReg Name="Scan3dPrincipalPointU" NameSpace="Standard">
    <Address>0xA038</Address><Length>8</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Endianess>BigEndian</Endianess>
  </FloatReg>
  <FloatReg Name="Scan3dPrincipalPointV" NameSpace="Standard">
    <Address>0xA040</Address><Length>8</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Endianess>BigEndian</Endianess>
  </FloatReg>

  <Category Name="TransportLayerControl" NameSpace="Standard">
    <pFeature>PayloadSize</pFeature>
    <pFeature>GevHeartbeatTimeout</pFeature>
  </Category>
  <IntReg Name="GevHeartbeatTimeout" NameSpace="Standard">
    <ToolTip>Control channel heartbeat timeout (ms), GigE Vision bootstrap register 0x0938</ToolTip>
    <Address>0x0938</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <IntSwissKnife Name="PayloadSize" NameSpace="Standard">
    <pVariable Name="WIDTH">Width</pVariable>
    <pVariable Name="HEIGHT">Height</pVariable>
    <pVariable Name="PIXELFORMAT">PixelFormat</pVariable>
    <Formula>WIDTH * HEIGHT * ((PIXELFORMAT&gt;&gt;16)&amp;0xFF) / 8</Formula>
  </IntSwissKnife>
  <Integer Name="TLParamsLocked" NameSpace="Standard">
    <Visibility>Invisible</Visibility><Value>0</Value><Min>0</Min><Max>1</Max>
  </Integer>

  <Port Name="Device" NameSpace="Standard"/>
</RegisterDescription>
)xml";

}  // namespace fettle::sim::detail
